"""The scans of a scene before registration: a folder read into ``Scan``s, each once for its checks (``load_scene``),
and the checks that skip a scan (too few points, all coinciding, a stray point far away, another unit: ``same_units``)
or refuse a scene (names the results cannot hold, fewer than two scans, a voxel no grid can take), each with its
one-line reason; ``voxel_doubt`` says why nothing may have registered."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from sghr_gtsam.config import Config
from sghr_gtsam.features.local import MAX_CELLS, voxel_from_spans
from sghr_gtsam.io.features import read_features
from sghr_gtsam.io.poses import shown_name, unwritable_name
from sghr_gtsam.io.scans import COORDINATE_LIMIT, check_memory, finite_points, left_out, list_scans, load_scan
from sghr_gtsam.types import InputError, Scan, ScanStats

Log = Callable[[str], None]


def load_scene(folder: str | Path, config: Config, log: Log = print) -> tuple[list[Scan], dict[str, str]]:
    """The scans of ``folder``, each read once for its checks and ``ScanStats`` (its points are not kept: the
    stages read them again), with its keypoints and descriptors from ``config.features`` if set; unusable files
    and scans without features are skipped with a reason instead of failing the run. ``InputError`` before reading
    a scan that would not fit in the memory available (``io.scans.check_memory``)."""
    scans: list[Scan] = []
    skipped: dict[str, str] = {}
    digests: dict[str, str] = {}
    for path in list_scans(folder):
        if why := unwritable_name(path.name):  # the results name scans by their file names
            skipped[path.name] = f"its name {path.name!r} {why} in the pose files: rename it"
            log(f"skipped {shown_name(path.name)}: {skipped[path.name]}")
            continue
        check_memory(path)  # a scan too large for this machine ends the run: it is no bad file to skip
        try:
            P, dropped = finite_points(load_scan(path))
        except InputError as e:
            skipped[path.name] = str(e)
            log(f"skipped {path.name}: {e}")
            continue
        if dropped:
            log(f"{path.name}: dropped {dropped} points not finite or past ±{COORDINATE_LIMIT:.2g}")
        if sparse := _too_sparse(len(P), config.min_points):
            skipped[path.name] = sparse
            log(f"skipped {path.name}: {sparse}")
            continue
        stats = ScanStats.of(P)
        if coarse := _float32_rounding(P, stats.extent):
            skipped[path.name] = coarse
            log(f"skipped {path.name}: {coarse}")
            continue
        del P  # the stages read the scan again when they need its points: none holds every scan's at once
        if stats.digest in digests:
            log(f"note: {path.name} holds the same points as {digests[stats.digest]}")
        digests.setdefault(stats.digest, path.name)
        scans.append(Scan(path.name, path, stats=stats))
    if config.features:
        given = read_features(config.features, [Path(s.name).stem for s in scans])
        for s in scans:
            s.keypoints = given.get(Path(s.name).stem)
            if s.keypoints is None:
                skipped[s.name] = f"no keypoints and descriptors in {config.features}"
                log(f"skipped {s.name}: {skipped[s.name]}")
        scans = [s for s in scans if s.keypoints is not None]
    if len(scans) < 2:
        raise too_few(scans, skipped, f"{folder}: ")
    for name in left_out(folder):  # said once the scene is read: an error stays the one line printed
        log(f"not a scan, by its name: {shown_name(name)} (poses, a trajectory, overlaps or a readme)")
    return scans, skipped


FLOAT32_RATIO = 50.0
"""A scan whose coordinates are all float32 values, at a magnitude where float32's steps exceed 1/this of its extent,
is skipped: it lost its shape to rounding where it was written (float32 keeps 24 bits: steps of 0.25 m at
2·10⁶ m, UTM northings), and the default voxel is 1/100 of the extent. Four 6.3 m room scans stored as float32
register at 5·10⁵ (steps of 1/100 of their extent) and none at 2·10⁶ (1/25: "no pair could be registered")."""


def _float32_rounding(points: np.ndarray, extent: float) -> str | None:
    """Why ``points`` (finite, float64) are too coarse to register, rounded to float32 (``FLOAT32_RATIO``), or
    None. Told from the values (every one a float32) rather than the file's type, for every reader alike."""
    sample = points[:: max(1, len(points) // 10_000)]
    if extent <= 0 or not np.array_equal(sample, sample.astype(np.float32)):
        return None
    size = float(np.abs(points).max())
    step = float(np.spacing(np.float32(size)))
    if step * FLOAT32_RATIO <= extent:
        return None
    return (
        f"its coordinates are float32 values up to {size:.3g}, where float32 rounds to steps of {step:.3g}, "
        f"1/{extent / step:.3g} of its extent {extent:.3g}: the precision was lost where it was written "
        f"(store such coordinates as float64, or with the offset taken out)"
    )


def too_few(scans: list[Scan], skipped: dict[str, str], where: str = "") -> InputError:
    """The error of a run left with fewer than two scans, naming the first skipped one and why."""
    first = next(iter(skipped.items()), None)
    why = f"; skipped {shown_name(first[0])}: {first[1]}" if first else ""
    more = f" (and {len(skipped) - 1} more)" if len(skipped) > 1 else ""
    return InputError(f"{where}need at least 2 usable scans, {len(scans)} left{why}{more}")


def check_given(scans: list[Scan], scores: np.ndarray | None) -> np.ndarray | None:
    """``InputError`` unless there are two scans or more, named as the results can hold (``check_names``), with
    keypoints and descriptors of one dimension for all of them or none, and ``scores`` (given overlap scores, or None)
    an (N, N) finite symmetric matrix; the scores as floats."""
    if len(scans) < 2:
        raise InputError(f"need at least 2 scans, got {len(scans)}")
    check_names([s.name for s in scans])
    given = sum(s.keypoints is not None for s in scans)
    if 0 < given < len(scans):
        raise InputError(f"{given} of {len(scans)} scans have keypoints and descriptors: give them for all or none")
    if len({s.keypoints.descriptors.shape[1] for s in scans if s.keypoints is not None}) > 1:
        raise InputError("the scans' descriptors differ in dimension")
    return None if scores is None else given_scores(scores, len(scans))


def usable_scans(
    scans: list[Scan],
    stats: list[ScanStats],
    scores: np.ndarray | None,
    skipped: dict[str, str],
    log: Log,
    min_points: int,
) -> tuple[list[Scan], list[ScanStats], np.ndarray | None]:
    """The scans ``same_units`` keeps, their ``stats`` and the rows of ``scores`` (given for every scan) that stay;
    the others are named in ``skipped``. ``InputError`` (``too_few``) when fewer than two are left."""
    keep = same_units(scans, stats, skipped, log, min_points)
    if len(keep) < 2:
        raise too_few([scans[k] for k in keep], skipped)
    return [scans[k] for k in keep], [stats[k] for k in keep], None if scores is None else scores[np.ix_(keep, keep)]


def scene_voxel(voxel: float | None, stats: list[ScanStats]) -> float:
    """The grid of the run: ``voxel`` if given (``Config.voxel``), else ``voxel_from_spans`` of the scans. A voxel
    so small that the median scan cannot fit the grid along some axis is refused: each scan would be skipped as if
    a stray point had stretched it."""
    voxel = voxel if voxel else voxel_from_spans([st.span for st in stats])
    if (cells := float(np.median([st.span for st in stats])) / voxel) >= np.sqrt(3) * MAX_CELLS:
        raise InputError(
            f"voxel {voxel:.3g} is too small: the median scan's diagonal spans {cells:.3g} voxels of it "
            f"(at most 2^31 along an axis)"
        )
    return voxel


def given_scores(scores: np.ndarray, n: int) -> np.ndarray:
    S = np.asarray(scores, dtype=float)
    if S.shape != (n, n):
        raise InputError(f"overlap scores must be a {n}x{n} matrix (one row a scan given), got shape {S.shape}")
    if not np.all(np.isfinite(S)) or not np.allclose(S, S.T):
        raise InputError("overlap scores must be finite and symmetric")
    return S


def check_names(names: list) -> None:
    """``InputError`` unless every scan name is distinct and a pose file can hold it (``io.poses.unwritable_name``):
    results are matched to scans by name, and pose files hold one name a line, read back stripped."""
    seen: set[str] = set()
    for name in names:
        if why := unwritable_name(name):
            raise InputError(
                f"scan name {name!r} {why} (pose files hold one name a line, read back stripped, '#' "
                f"starting a comment)"
            )
        if name in seen:
            raise InputError(f"two scans are named {name!r}")
        seen.add(name)


def _too_sparse(points: int, min_points: int) -> str | None:
    """Why a scan of ``points`` finite points is skipped (``Config.min_points``), or None."""
    return f"only {points} finite points (< {min_points})" if points < min_points else None


UNIT_RATIO = 30.0
"""A scan whose extent (1st-99th percentile box diagonal) differs from the median scan's by more than this factor
is skipped as in another unit or of another scene (a scan in millimetres among scans in metres: 1000×; a small
object among room scans: 33×)."""


STRAY_RATIO = 1e6
"""A scan whose bounding box is this many times larger than the box of 98 % of its points holds stray points far
away (one point at 1e9 m in a 10 m room); it is skipped, since it would also set the scene's voxel size."""


def same_units(
    scans: list[Scan], stats: list[ScanStats], skipped: dict[str, str], log: Log, min_points: int
) -> list[int]:
    """The indices of the scans with at least ``min_points`` finite points whose points do not all coincide, hold no
    stray point far away and whose extent is within ``UNIT_RATIO`` of the median scan's (from their ``stats``); the
    others are named in ``skipped``."""
    extents = np.array([st.extent for st in stats])
    spans = np.array([st.span for st in stats])
    flat, stray = spans <= 0, spans > STRAY_RATIO * extents
    sparse = [_too_sparse(st.points, min_points) for st in stats]
    usable = ~flat & ~stray & np.array([why is None for why in sparse])
    median = float(np.median(extents[usable])) if usable.any() else 0.0
    keep = []
    for k, (s, extent, span, is_flat, is_stray, too_sparse) in enumerate(
        zip(scans, extents, spans, flat, stray, sparse)
    ):
        ratio = extent / median if median > 0 else 1.0
        if too_sparse:
            skipped[s.name] = too_sparse
        elif is_flat:
            skipped[s.name] = "all its points coincide"
        elif is_stray:
            skipped[s.name] = f"its points span {span:.3g} but 98 % of them {extent:.3g}: a stray point far away?"
        elif not 1 / UNIT_RATIO <= ratio <= UNIT_RATIO:
            skipped[s.name] = (
                f"its extent {extent:.3g} is {ratio:.3g}x the median scan's {median:.3g}: another unit "
                f"or another scene?"
            )
        else:
            keep.append(k)
            continue
        log(f"skipped {s.name}: {skipped[s.name]}")
    return keep


VOXEL_DOUBT = 10.0
"""A voxel this many times finer or coarser than the default is named when no pair registers: FPFH's neighbourhoods
(5 voxels) then hold one point each, or a scan is a handful of cells; either way nothing matches."""


EXTENT_RATIO = 3.0
"""When no pair registers with the default voxel, the scans whose extent is this many times the median scan's, or
1/this of it, are named: a majority of scans of noise or of another scene sets the median, and so the voxel (two room
scans among three small clouds of noise: 1/10 of the rooms' voxel). Real scans (3DMatch, objects) are within 1.3x."""


def voxel_doubt(voxel: float, scans: list[Scan], given: bool) -> str:
    """Why ``voxel`` may be what kept every pair from registering, or "": a ``given`` one far from the default, or a
    default that scans far from the others set."""
    spans = np.array([s.stats.span for s in scans])
    if given:
        default = voxel_from_spans(spans)
        ratio = voxel / default
        if 1 / VOXEL_DOUBT <= ratio <= VOXEL_DOUBT:
            return ""
        times = f"{ratio:.3g}x" if np.isfinite(ratio) else "beyond any multiple of"  # 1e308 / 0.07 overflows
        return (
            f" is the voxel {voxel:.3g} right? it is {times} the default {default:.3g}, 1/100 of the median "
            f"scan's extent"
        )
    ratios = spans / (100 * voxel)
    far = [
        f"{s.name} ({ratio:.2g}x)" for s, ratio in zip(scans, ratios) if not 1 / EXTENT_RATIO <= ratio <= EXTENT_RATIO
    ]
    if not far:
        return ""
    named = ", ".join(far[:3]) + (f" and {len(far) - 3} more" if len(far) > 3 else "")
    return (
        f" is the voxel {voxel:.3g} right? it is 1/100 of the median scan's extent ({100 * voxel:.3g}), and "
        f"{named} differ{'s' if len(far) == 1 else ''} from it by more than {EXTENT_RATIO:g}x: scans of noise or of "
        f"another scene may have set the median (leave them out, or set --voxel)"
    )
