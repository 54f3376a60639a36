"""Distinct grid cells (sghr_gtsam.cells): the same rows, order and inverse as numpy's row-wise unique."""

import numpy as np
from hypothesis import example, given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from sghr_gtsam.cells import unique_cells

_COORDINATES = st.one_of(st.integers(-5, 5), st.integers(-(2**62), 2**62))  # small spans, and spans past one key


_WRAP = 2**62  # a span of 2**63 wraps to a negative int64: found by hypothesis in CI


@given(arrays(np.int64, st.tuples(st.integers(0, 200), st.just(3)), elements=_COORDINATES))
@example(np.array([[_WRAP, -_WRAP, -_WRAP], [-_WRAP, -_WRAP, -_WRAP]]))
@example(np.array([[-_WRAP, 0, _WRAP], [-_WRAP, -_WRAP, -_WRAP]]))
@example(np.array([[0, 0, -_WRAP], [_WRAP, -_WRAP, -_WRAP], [-_WRAP, -_WRAP, -_WRAP]]))
def test_unique_cells_is_numpys_row_unique(cells):
    rows, inverse = unique_cells(cells)
    expected, expected_inverse = np.unique(cells, axis=0, return_inverse=True)
    np.testing.assert_array_equal(rows, expected)
    np.testing.assert_array_equal(inverse, expected_inverse.ravel())
    np.testing.assert_array_equal(rows[inverse], cells)
