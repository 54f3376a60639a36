import signal
from pathlib import Path

import pytest

from data_tools.scene_gt import data_root
from sghr_gtsam.features.local import default_voxel
from sghr_gtsam.io.poses import read_poses
from sghr_gtsam.io.scans import load_scan

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


def _scene(data_dir: Path, folder: str, gt_file: str) -> tuple[dict, dict, float]:
    """GT poses and scans by name, and the default voxel, of a real scene."""
    names, poses = read_poses(data_dir / gt_file)
    scans = {n: load_scan(data_dir / folder / n) for n in names}
    return dict(zip(names, poses)), scans, default_voxel(list(scans.values()))


@pytest.fixture(scope="module")
def kitchen(data_dir):
    """The 3DMatch kitchen fragments (``_scene``)."""
    return _scene(data_dir, "kitchen", "kitchen/gt/gt_poses.txt")


@pytest.fixture(scope="module")
def bunny(data_dir):
    """The Stanford bunny's scans (``_scene``)."""
    return _scene(data_dir, "bunny", "bunny/gt_poses.txt")
