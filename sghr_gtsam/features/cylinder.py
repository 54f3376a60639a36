"""A rotation-invariant local descriptor with a wider view than FPFH: the scan's surface around each point, binned
in a cylinder about the point's normal (radial × height × azimuth, like a spin image with its azimuth kept), made
invariant to the turn about the normal by the magnitudes of the azimuth's first Fourier harmonics.

FPFH describes a 5-voxel neighbourhood by angles between normals, which repeat wherever furniture repeats; this
descriptor sees 12 voxels (half a metre on a 3DMatch fragment) of where the surface is. On the shared 3DMatch
scenes it gets more gt.log pairs right than FPFH with the same estimator (docs/BENCHMARKS.md, issue 10).
No axis in the tangent plane is needed (the least repeatable part of a local reference frame): only the normal,
estimated at 4 voxels, so that sensor noise at one voxel does not turn it.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

SUPPORT = 2.0
"""Grid of the points the cylinders count, in voxels: the shape at half a metre needs no finer sampling, and
it cuts the neighbours a point counts by four."""
AXIS_RADIUS = 4.0
"""Radius of the neighbourhood whose principal axes give the cylinder's axis (the normal), in voxels."""
RADIUS = 12.0
"""Cylinder radius and half height, in voxels."""
BINS = (4, 4)
"""Radial and height bins."""
HARMONICS = 5
"""Azimuth harmonics kept per bin (0 = the spin image's count): the descriptor has radial × height × harmonics
values."""


def _axes(points: np.ndarray, d: np.ndarray, owner: np.ndarray, radius: float, sensor: np.ndarray) -> np.ndarray:
    """Unit normals (M, 3): the least principal axis of the offsets ``d`` (of ``owner``'s neighbours) within
    ``radius``, towards ``sensor``."""
    near = np.einsum("ij,ij->i", d, d) <= radius * radius
    d, owner, n = d[near], owner[near], len(points)
    weight = 1.0 / np.maximum(np.bincount(owner, minlength=n), 1)
    mean = np.stack([np.bincount(owner, d[:, a], n) for a in range(3)], 1) * weight[:, None]
    second = np.stack([np.bincount(owner, d[:, a] * d[:, b], n) for a in range(3) for b in range(3)], 1)
    covariance = second.reshape(n, 3, 3) * weight[:, None, None] - mean[:, :, None] * mean[:, None, :]
    z = np.linalg.eigh(covariance)[1][:, :, 0]
    z[np.einsum("ij,ij->i", z, sensor - points) < 0] *= -1
    return z


def cylinder_descriptors(points: np.ndarray, voxel: float, sensor: np.ndarray | None = None) -> np.ndarray:
    """Descriptors (M, 80) float32, unit length, of the grid ``points`` (M, 3) of one scan, ``voxel`` its grid;
    normals point towards ``sensor`` (default: the origin), as ``compute_features``' do."""
    points = np.asarray(points, dtype=np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(SUPPORT * voxel)
    return _describe(points, np.asarray(pcd.points), voxel, np.zeros(3) if sensor is None else sensor)


def _describe(points: np.ndarray, support: np.ndarray, voxel: float, sensor: np.ndarray) -> np.ndarray:
    """``cylinder_descriptors`` of ``points`` counting the ``support`` points."""
    sensor = np.asarray(sensor, dtype=float)
    radius, (n_rho, n_h) = RADIUS * voxel, BINS
    found = cKDTree(support).query_ball_point(points, radius, workers=-1)
    counts = np.fromiter(map(len, found), dtype=np.int64, count=len(found))
    owner = np.repeat(np.arange(len(points)), counts)
    d = support[np.concatenate(found).astype(np.int64)] - points[owner]
    z = _axes(points, d, owner, AXIS_RADIUS * voxel, sensor)

    # The azimuth in any tangent basis (x, y): the harmonics' magnitudes do not depend on where it starts.
    helper = np.where(np.abs(z[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    x = np.cross(z, helper)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    h = np.einsum("ij,ij->i", d, z[owner])
    along_x = np.einsum("ij,ij->i", d, x[owner])
    along_y = np.einsum("ij,ij->i", d, np.cross(z, x)[owner])
    rho = np.hypot(along_x, along_y)
    turn = (along_x - 1j * along_y) / np.maximum(rho, 1e-12 * radius)  # e^{-i phi}
    i_rho = np.minimum((rho / radius * n_rho).astype(np.int64), n_rho - 1)
    i_h = np.clip(((h / radius + 1.0) / 2.0 * n_h).astype(np.int64), 0, n_h - 1)
    cell = (owner * n_rho + i_rho) * n_h + i_h
    m, cells = len(points), len(points) * n_rho * n_h
    D = np.empty((m, n_rho * n_h, HARMONICS))
    power = np.ones(len(cell), dtype=complex)
    for k in range(HARMONICS):  # |sum of e^{-ik phi}| over the cell's points: invariant to the turn about z
        D[:, :, k] = np.hypot(np.bincount(cell, power.real, cells),
                              np.bincount(cell, power.imag, cells)).reshape(m, -1)
        power *= turn
    D /= np.maximum(counts, 1)[:, None, None]
    # sqrt: a Hellinger-like scale, so that a few full cells do not outweigh the shape's outline
    D = np.sqrt(D).reshape(m, -1)
    return np.ascontiguousarray(D / np.maximum(np.linalg.norm(D, axis=1, keepdims=True), 1e-12), dtype=np.float32)
