"""Rotation matrices ↔ unit quaternions, Hamilton convention, scalar first (w, x, y, z).

This is the convention of COLMAP's images.txt/.bin (``QW QX QY QZ``), the reference 3DGS
``qvec2rotmat``/``rotmat2qvec`` and the 3DGS PLY ``rot_0..3``. pycolmap's ``Rotation3d.quat`` is
Eigen's coefficient order (x, y, z, w): reorder before comparing with it.
"""

from __future__ import annotations

import numpy as np

# A rotation's rows are orthonormal to rounding; anything much further off is a caller's bug
# (a reflection or a scaled matrix), which no quaternion represents.
ORTHONORMAL_TOLERANCE = 1e-6


def _check_rotations(matrices: np.ndarray) -> None:
    gram = np.einsum("nij,nkj->nik", matrices, matrices)
    off = np.max(np.abs(gram - np.eye(3)), axis=(1, 2)) if len(matrices) else np.zeros(0)
    det = np.linalg.det(matrices) if len(matrices) else np.zeros(0)
    bad = ~np.isfinite(off) | (off > ORTHONORMAL_TOLERANCE) | (det < 0)
    if np.any(bad):
        index = int(np.argmax(bad))
        raise ValueError(f"matrix {index} is not a rotation (|RRᵀ − I| = {off[index]:.3g}, det = {det[index]:.6g})")


def rotation_to_quaternion(rotations: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) with w ≥ 0 of rotation matrices, (3, 3) → (4,) or (N, 3, 3) → (N, 4).

    Shepperd's method: the quaternion component of largest magnitude comes from a square root
    of the diagonal, the other three from off-diagonal sums divided by it. Taking the largest
    keeps the divisor ≥ 1/2, so 180° turns (trace −1, w = 0) are as exact as the identity,
    which the naive ``w = √(1 + trace)/2`` formula is not.
    """
    matrices = np.asarray(rotations, dtype=np.float64)
    single = matrices.ndim == 2
    matrices = matrices[None] if single else matrices
    if matrices.ndim != 3 or matrices.shape[1:] != (3, 3):
        raise ValueError(f"rotations must be (3, 3) or (N, 3, 3), got {np.shape(rotations)}")
    _check_rotations(matrices)

    m = matrices
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    # 4·q_k² for k = w, x, y, z; the largest picks the branch.
    squares = np.stack(
        (
            1.0 + trace,
            1.0 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
            1.0 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
            1.0 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2],
        ),
        axis=1,
    )
    branch = np.argmax(squares, axis=1)
    # Pairwise sums/differences of the off-diagonal elements: 4·q_i·q_j for each pair.
    wx = m[:, 2, 1] - m[:, 1, 2]
    wy = m[:, 0, 2] - m[:, 2, 0]
    wz = m[:, 1, 0] - m[:, 0, 1]
    xy = m[:, 0, 1] + m[:, 1, 0]
    xz = m[:, 0, 2] + m[:, 2, 0]
    yz = m[:, 1, 2] + m[:, 2, 1]
    products = np.stack(
        (
            np.stack((squares[:, 0], wx, wy, wz), axis=1),  # 4w·(w, x, y, z)
            np.stack((wx, squares[:, 1], xy, xz), axis=1),  # 4x·(w, x, y, z)
            np.stack((wy, xy, squares[:, 2], yz), axis=1),  # 4y·(w, x, y, z)
            np.stack((wz, xz, yz, squares[:, 3]), axis=1),  # 4z·(w, x, y, z)
        ),
        axis=1,
    )
    rows = np.arange(len(m))
    chosen = products[rows, branch]
    pivot = np.sqrt(np.maximum(squares[rows, branch], 0.0))  # = 2|q_branch| ≥ 1
    quaternions = chosen / (2.0 * pivot[:, None])
    quaternions /= np.linalg.norm(quaternions, axis=1, keepdims=True)
    # q and −q are the same rotation; COLMAP and 3DGS's rotmat2qvec keep w ≥ 0.
    quaternions[quaternions[:, 0] < 0] *= -1.0
    quaternions += 0.0  # turns −0.0 into 0.0, so a 180° turn is not written as "-0.0"
    return quaternions[0] if single else quaternions


def quaternion_to_rotation(quaternions: np.ndarray) -> np.ndarray:
    """Rotation matrices of quaternions (w, x, y, z), (4,) → (3, 3) or (N, 4) → (N, 3, 3).

    Quaternions are normalised first, as COLMAP does when it reads a model, so a qvec written
    with few digits still gives an orthonormal matrix. A zero (or non-finite) quaternion has
    no direction to normalise and raises ValueError.
    """
    q = np.asarray(quaternions, dtype=np.float64)
    single = q.ndim == 1
    q = q.reshape(1, -1) if single else q
    if q.ndim != 2 or q.shape[1] != 4:
        raise ValueError(f"quaternions must be (4,) or (N, 4), got {np.shape(quaternions)}")
    norms = np.linalg.norm(q, axis=1)
    bad = ~np.isfinite(norms) | (norms < 1e-12)
    if np.any(bad):
        index = int(np.argmax(bad))
        raise ValueError(f"quaternion {index} {q[index].tolist()} has zero or non-finite norm: it is not a rotation")
    w, x, y, z = (q / norms[:, None]).T
    matrices = np.stack(
        (
            np.stack((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)), axis=1),
            np.stack((2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)), axis=1),
            np.stack((2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)), axis=1),
        ),
        axis=1,
    )
    return matrices[0] if single else matrices
