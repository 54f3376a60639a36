"""data_tools.resync: a run's final pose graph, rebuilt from its results folder, synchronizes to the run's own
answer."""

import numpy as np

from data_tools.resync import KEPT, main, run_graph
from sghr_gtsam.config import Config
from sghr_gtsam.io.poses import read_poses
from sghr_gtsam.pipeline import run
from sghr_gtsam.se3 import inv_T, relative_errors
from sghr_gtsam.sync import synchronize
from sghr_gtsam.synthetic import make_scene, write_scene


def test_a_runs_graph_synchronizes_again_to_its_poses_and_kept_edges(tmp_path):
    """The 16-scan hotel: its stacked rooms leave rejected registrations beside the kept ones, so the weights and
    statuses read back from edges.csv decide which edges synchronization keeps."""
    write_scene(make_scene("hotel", 16, seed=0), tmp_path / "scene")
    result = run(tmp_path / "scene", tmp_path / "out", Config(record=False, workers=1), log=lambda m: None)
    graph, scans, status = run_graph(tmp_path / "out")
    assert scans == result.names and graph.num_edges == result.graph.num_edges
    assert not set(status) <= set(KEPT)  # some registrations the run did not keep
    again = synchronize(graph)
    np.testing.assert_array_equal(again.weights > 0, np.isin(status, KEPT))
    main([str(tmp_path / "out"), "--out", str(tmp_path / "poses.txt")])
    names, poses = read_poses(tmp_path / "poses.txt")
    ran = dict(zip(*read_poses(tmp_path / "out" / "poses.txt")))
    assert names == list(ran)
    before = np.stack([ran[n] for n in names])
    rot, trans = relative_errors(inv_T(poses[0])[None] @ poses, inv_T(before[0])[None] @ before)
    assert rot.max() < 1e-6 and trans.max() < 1e-6
