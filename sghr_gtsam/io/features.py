"""Reading precomputed keypoints and descriptors (for instance the SGHR authors' YOHO output).

Per scan, named by the stem of the scan's file name (``cloud_bin_0`` for ``cloud_bin_0.ply``):
``<stem>.kpts.npy``, a (K, 3) array of keypoints in the scan's own frame, and ``<stem>.desc.npy``, a
(K, D) array with row k describing keypoint k. Both may sit in the folder itself or in any sub-folder,
so the authors' layout (``kpts/`` and ``yoho/`` side by side) is read as it is.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sghr_gtsam.types import InputError, Keypoints

KEYPOINTS_SUFFIX = ".kpts.npy"
DESCRIPTORS_SUFFIX = ".desc.npy"


def find_feature_files(folder: str | Path) -> dict[str, dict[str, Path]]:
    """``{stem: {suffix: path}}`` for every keypoint and descriptor file under ``folder`` (recursive).
    Raises ``InputError`` when the folder does not exist, holds no such file, or holds one twice."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(
            f"features folder {folder} does not exist"
            if not folder.exists()
            else f"features path {folder} is not a folder"
        )
    found: dict[str, dict[str, Path]] = {}
    for suffix in (KEYPOINTS_SUFFIX, DESCRIPTORS_SUFFIX):
        for path in sorted(folder.rglob(f"*{suffix}")):
            if path.name.startswith(".") or not path.is_file():
                continue
            files = found.setdefault(path.name[: -len(suffix)], {})
            if suffix in files:
                raise InputError(f"features folder {folder} holds {path.name} twice: {files[suffix]} and {path}")
            files[suffix] = path
    if not found:
        raise InputError(f"no *{KEYPOINTS_SUFFIX} or *{DESCRIPTORS_SUFFIX} files in {folder} or its sub-folders")
    return found


def _load(path: Path) -> np.ndarray:
    try:
        with open(path, "rb") as f:
            if f.read(6) != b"\x93NUMPY":  # numpy's own message for other files talks about pickles
                raise InputError("not an .npy file")
            f.seek(0)
            return np.load(f, allow_pickle=False)
    except InputError as e:
        raise InputError(f"cannot read {path}: {e}") from None
    except Exception as e:  # noqa: BLE001 - any reader failure is bad input, reported on one line
        raise InputError(f"cannot read {path}: {' '.join(str(e).split()) or type(e).__name__}") from None


def read_features(folder: str | Path, stems: list[str]) -> dict[str, Keypoints]:
    """Keypoints and descriptors of each scan stem in ``stems`` that has both files under ``folder``.

    A stem with neither file is left out (the caller decides: the pipeline skips that scan). Raises a
    one-line ``InputError`` when a stem has only one of its two files, when a file is unreadable, has a
    bad shape, non-finite values or no rows, when the two files of a stem differ in row count, or when
    the descriptors of different scans differ in dimension.
    """
    files = find_feature_files(folder)
    out: dict[str, Keypoints] = {}
    for stem in stems:
        pair = files.get(stem)
        if not pair:
            continue
        if len(pair) == 1:
            (have,) = pair.values()
            missing = stem + (DESCRIPTORS_SUFFIX if KEYPOINTS_SUFFIX in pair else KEYPOINTS_SUFFIX)
            raise InputError(f"{have} has no matching {missing} in {folder} or its sub-folders")
        kpts, desc = pair[KEYPOINTS_SUFFIX], pair[DESCRIPTORS_SUFFIX]
        arrays = _load(kpts), _load(desc)
        try:
            out[stem] = Keypoints(*arrays)
        except InputError as e:
            raise InputError(f"bad features for {stem} ({kpts}, {desc}): {e}") from None
        first = next(iter(out))
        if out[stem].descriptors.shape[1] != out[first].descriptors.shape[1]:
            raise InputError(
                f"descriptors in {folder} differ in dimension: {first} has "
                f"{out[first].descriptors.shape[1]}, {stem} has {out[stem].descriptors.shape[1]}"
            )
    return out
