"""End to end on real scans with ground truth (../shared/data; skipped when absent)."""

import pytest

from data_tools.refit_gt import refit
from sghr_gtsam.config import Config
from sghr_gtsam.evaluate import fragment_id, registration_recall, scan_errors
from sghr_gtsam.io.poses import read_gt_info, read_gt_log, read_poses
from sghr_gtsam.io.scans import load_scan
from sghr_gtsam.pipeline import run


def _errors(result, gt_file):
    gt_names, gt = read_poses(gt_file)
    return scan_errors(result.names, result.poses, gt[[gt_names.index(n) for n in result.names]])


@pytest.fixture(scope="module")
def kitchen(data_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("kitchen")
    return run(data_dir / "kitchen", out, Config(record=False), log=lambda m: None)


@pytest.fixture(scope="module")
def bunny(data_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("bunny")
    return run(data_dir / "bunny", out, Config(record=False), log=lambda m: None)


def test_kitchen_registration_recall_is_complete(kitchen, data_dir):
    gt = data_dir / "kitchen" / "gt"
    keep = kitchen.registered
    ids = [fragment_id(kitchen.names[k]) for k in keep]
    rr = registration_recall(ids, kitchen.poses[keep], read_gt_log(gt / "gt.log"), read_gt_info(gt / "gt.info"))
    assert len(rr.pairs) >= 10
    assert rr.recall == 1.0, dict(zip(rr.pairs, rr.rmse.round(3)))


def test_kitchen_scans_within_5_deg_and_20_cm(kitchen, data_dir):
    names, gt = read_poses(data_dir / "kitchen" / "gt" / "gt_poses.txt")
    index = [names.index(n) for n in kitchen.names]
    err = scan_errors(kitchen.names, kitchen.poses, gt[index])
    report = {n: (round(r, 2), round(t, 3)) for n, r, t in zip(err.names, err.rotation_deg, err.translation)}
    assert err.within(5.0, 0.2).sum() >= 8, report
    # Every scan the tool does not flag must be right: a wrong pose is worse than a flag; a loose one is off by no
    # more than three of the σ it is reported with. Judged against the GT re-fitted to the scans: ICP started at the
    # shipped GT moves cloud_bin_21 by 2.4-3.0° / 0.15-0.22 m on each of its three pairs, so the scans themselves put
    # it farther from that GT than 0.2 m.
    refitted = refit([load_scan(data_dir / "kitchen" / n) for n in names], gt, 0.025).poses
    err = scan_errors(kitchen.names, kitchen.poses, refitted[index])
    ok = err.within(5.0, 0.2)
    registered = set(kitchen.registered)
    report = {n: (round(r, 2), round(t, 3)) for n, r, t in zip(err.names, err.rotation_deg, err.translation)}
    loose = kitchen.verdict.loose
    assert all(ok[k] for k in registered if kitchen.names[k] not in loose), (report, kitchen.unregistered)
    assert all(err.translation[kitchen.names.index(n)] <= 3 * v["sigma"] for n, v in loose.items()), (report, loose)
    # one part, every scan checked by a loop; a doubt here can only be a direction the overlap alone bounds
    assert [p.scans for p in kitchen.verdict.parts] == [kitchen.names]
    assert set(kitchen.verdict.doubts.values()) <= {"loose"}, kitchen.verdict.doubts


def test_bunny_all_scans_within_1_deg_and_1_mm(bunny, data_dir):
    err = _errors(bunny, data_dir / "bunny" / "gt_poses.txt")
    assert bunny.unregistered == [] and bunny.verdict.trusted() == bunny.names
    assert err.rotation_deg.max() <= 1.0, err.rotation_deg
    assert err.translation.max() <= 1e-3, err.translation
