import signal
from pathlib import Path

import pytest

from data_tools.scene_gt import data_root

# A non-interactive shell starts background jobs with SIGINT ignored, and a Python started so never raises
# KeyboardInterrupt: the tests that stop runs with SIGINT then failed when pytest ran in the background. Python's
# handler, installed here, also gives the runs these tests start the default action again (exec resets it).
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

DATA = data_root()


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared real data (MANIFEST.md); skips the test when it is not there."""
    if not (DATA / "MANIFEST.md").is_file():
        pytest.skip(f"real data not found at {DATA} (set SGHR_DATA to ../shared/data)")
    return DATA
