import os
from pathlib import Path

import pytest

DATA = Path(os.environ.get("SGHR_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared real data (MANIFEST.md); skips the test when it is not there."""
    if not (DATA / "MANIFEST.md").is_file():
        pytest.skip(f"real data not found at {DATA} (set SGHR_DATA to ../shared/data)")
    return DATA
