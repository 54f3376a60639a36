"""Hostile input to ``sync``: each case asserts the one line the user gets (never a traceback), the exit code and
what is left beside the input (tests/test_corpus.py holds the rest of the corpus)."""

from __future__ import annotations

import os

import numpy as np
import pytest
from typer.testing import CliRunner

from sghr_gtsam.cli import app
from sghr_gtsam.io.g2o import read_g2o
from sghr_gtsam.se3 import inv_T

runner = CliRunner()

_V = "VERTEX_SE3:QUAT {} 0 0 0 0 0 0 1\n"
_INFO = " ".join("1" if r == c else "0" for r in range(6) for c in range(r, 6))


def _upper(M: np.ndarray) -> str:
    """A g2o edge's 21 information values of ``M`` (g2o order: translation first)."""
    return " ".join(repr(float(M[r, c])) for r in range(6) for c in range(r, 6))


def _edge(a, b, pose="1 0 0 0 0 0 1", info=_INFO) -> str:
    return f"EDGE_SE3:QUAT {a} {b} {pose} {info}\n"


def _cli(*args) -> tuple[int, list[str]]:
    r = runner.invoke(app, [str(a) for a in args])
    assert "Traceback" not in r.output, r.output
    assert r.exception is None or isinstance(r.exception, SystemExit), repr(r.exception)
    return r.exit_code, r.output.strip().splitlines()


def _triangle(first: str = "1 0 0 0 0 0 1", info: str = _INFO) -> str:
    """Three vertices and the three edges of a noise-free loop, ``first`` the pose of edge 0-1."""
    return (
        _V.format(0)
        + _V.format(1)
        + _V.format(2)
        + _edge(0, 1, first, info)
        + _edge(1, 2, "0 1 0 0 0 0 1")
        + _edge(0, 2, "1 1 0 0 0 0 1")
    )


@pytest.mark.parametrize("scale", ["1e-200", "1e300", "5e-324"])
def test_a_quaternion_of_any_finite_nonzero_scale_is_normalised(tmp_path, scale):
    """1e-200 was refused as a zero quaternion while 1e300 was accepted: both are directions."""
    (tmp_path / "in.g2o").write_text(_triangle(f"1 0 0 0 0 0 {scale}"))
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o")
    assert code == 0, lines
    _, poses, _ = read_g2o(tmp_path / "out.g2o")
    np.testing.assert_allclose((inv_T(poses[0]) @ poses[1])[:3], np.c_[np.eye(3), [1, 0, 0]], atol=1e-9)


def test_a_zero_quaternion_is_still_refused(tmp_path):
    (tmp_path / "in.g2o").write_text(_triangle("1 0 0 0 0 0 0"))
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o")
    assert code == 2 and len(lines) == 1 and "line 4: pose is not finite or its quaternion is zero" in lines[0]


@pytest.mark.parametrize("how", ["same path", "symbolic link", "hard link", "rejected beside it"])
def test_sync_never_writes_over_its_input(tmp_path, how):
    source = tmp_path / "in.g2o"
    source.write_text(_triangle())
    before = source.read_text()
    if how == "same path":
        out = source
    elif how == "symbolic link":
        out = tmp_path / "link.g2o"
        out.symlink_to(source)
    elif how == "hard link":
        out = tmp_path / "hard.g2o"
        os.link(source, out)
    else:  # OUT's dropped edges would go to OUT_rejected.g2o, which is the input
        source = source.rename(tmp_path / "o_rejected.g2o")
        out = tmp_path / "o.g2o"
    code, lines = _cli("sync", source, "--out", out)
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and "is the input file" in lines[0], lines
    assert source.read_text() == before
    assert not (tmp_path / "o.g2o").exists()


def test_isotropic_noise_writes_the_input_information(tmp_path):
    """``--noise isotropic`` solves with SE-Sync's precisions but writes each edge's own information, as read."""
    M = np.diag([4.0, 5.0, 6.0, 100.0, 200.0, 300.0])
    M[0, 4] = M[4, 0] = 1.5  # couples x with the y-rotation
    (tmp_path / "in.g2o").write_text(_triangle(info=_upper(M)))
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o", "--noise", "isotropic")
    assert code == 0, lines
    _, _, written = read_g2o(tmp_path / "out.g2o")
    _, _, given = read_g2o(tmp_path / "in.g2o")
    np.testing.assert_array_equal(written.information, given.information)


def _indefinite() -> np.ndarray:
    """Information (g2o order) whose blocks are positive definite and whole is not (eigenvalue −1)."""
    M = np.eye(6)
    M[0, 3] = M[3, 0] = 2.0
    return M


def test_indefinite_information_is_accepted_with_isotropic_noise_and_named(tmp_path):
    """SE-Sync's isotropic precisions use only the blocks; the edge is named in a warning, written out as given."""
    (tmp_path / "in.g2o").write_text(_triangle(info=_upper(_indefinite())))
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o", "--noise", "isotropic")
    assert code == 0, lines
    warnings = [line for line in lines if line.startswith("warning:")]
    assert len(warnings) == 1 and "line(s) 4" in warnings[0] and "not positive definite" in warnings[0], lines
    assert any("3 kept" in line for line in lines), lines
    _, poses, written = read_g2o(tmp_path / "out.g2o", indefinite=True)
    _, _, given = read_g2o(tmp_path / "in.g2o", indefinite=True)
    np.testing.assert_array_equal(written.information, given.information)
    np.testing.assert_allclose((inv_T(poses[0]) @ poses[2])[:3, 3], [1, 1, 0], atol=1e-6)


def test_indefinite_information_is_refused_in_one_line_where_the_noise_model_needs_it(tmp_path):
    (tmp_path / "in.g2o").write_text(_triangle(info=_upper(_indefinite())))
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o")
    assert code == 2 and len(lines) == 1 and "line 4: information matrix is not positive definite" in lines[0], lines
    M = np.eye(6)
    M[0, 1] = M[1, 0] = 2.0  # the translation block itself indefinite: no isotropic precision either
    (tmp_path / "in.g2o").write_text(_triangle(info=_upper(M)))
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o", "--noise", "isotropic")
    assert code == 2 and len(lines) == 1 and "line 4: information's rotation or translation block" in lines[0], lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.g2o"]
