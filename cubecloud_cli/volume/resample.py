"""Separable, anti-aliased resampling of a volume onto an axis-aligned grid.

Each output axis is a 1D map from output index ``o`` to a continuous input index
``c = scale * (o + 0.5) - 0.5 + offset`` (voxel centres at integer indices). Along each axis the
resampling is a matrix W (n_out × n_in) whose rows are non-negative and sum to 1, applied with one
BLAS matrix product; the 3D result is the product of the three. Hence:

* the output is a convex combination of input voxels: it never leaves the input's value range;
* linear (the default) uses a tent filter widened by the scale factor when downsampling, so it
  averages over the input voxels an output voxel covers (anti-aliasing), and is plain linear
  interpolation when upsampling;
* nearest picks the nearest input voxel (the resize the paper's CuNeRF data used);
* output voxels whose centre lies outside the input get 0 (air, after windowing).
"""

from __future__ import annotations

from typing import Literal, Sequence

import numpy as np

Interpolation = Literal["linear", "nearest"]

# Rounding slack so an output centre that lands exactly on the input's outer edge counts as inside.
_EDGE_TOLERANCE = 1e-6


def interpolation_matrix(
    n_in: int, n_out: int, scale: float, offset: float, method: Interpolation = "linear"
) -> np.ndarray:
    """The n_out × n_in float32 matrix of one axis (see module docstring for the mapping)."""
    if n_in < 1 or n_out < 1 or not (np.isfinite(scale) and scale > 0) or not np.isfinite(offset):
        raise ValueError(f"bad axis mapping: n_in={n_in}, n_out={n_out}, scale={scale}, offset={offset}")
    centres = scale * (np.arange(n_out, dtype=np.float64) + 0.5) - 0.5 + offset
    inside = (centres >= -0.5 - _EDGE_TOLERANCE) & (centres <= n_in - 0.5 + _EDGE_TOLERANCE)
    matrix = np.zeros((n_out, n_in), dtype=np.float64)
    rows = np.flatnonzero(inside)
    if method == "nearest":
        nearest = np.clip(np.floor(centres[rows] + 0.5), 0, n_in - 1).astype(np.int64)
        matrix[rows, nearest] = 1.0
    elif method == "linear":
        support = max(1.0, scale)
        distance = np.abs(np.arange(n_in)[None, :] - centres[rows, None]) / support
        weights = np.maximum(0.0, 1.0 - distance)
        # A centre within half a voxel of the edge may see only the edge voxel (or, for a very
        # narrow kernel, none): renormalising clamps to the edge value.
        totals = weights.sum(axis=1, keepdims=True)
        edge = np.clip(np.floor(centres[rows] + 0.5), 0, n_in - 1).astype(np.int64)
        empty = totals[:, 0] <= 0
        weights[empty, edge[empty]] = 1.0
        totals[empty] = 1.0
        matrix[rows] = weights / totals
    else:
        raise ValueError(f"unknown interpolation {method!r}")
    return matrix.astype(np.float32)


def resample_axes(volume: np.ndarray, matrices: Sequence[np.ndarray]) -> np.ndarray:
    """Apply one matrix per axis: ``out[a,b,c] = Σ W0[a,i] W1[b,j] W2[c,k] v[i,j,k]``.

    Axes are processed smallest-output-first so later products run on less data; the input may
    be any float array view (it is not modified).
    """
    if volume.ndim != 3 or len(matrices) != 3:
        raise ValueError("resample_axes needs a 3D volume and three matrices")
    for axis, matrix in enumerate(matrices):
        if matrix.shape[1] != volume.shape[axis]:
            raise ValueError(f"matrix {axis} has {matrix.shape[1]} columns, axis has {volume.shape[axis]} voxels")
    current = np.ascontiguousarray(volume, dtype=np.float32)
    order = sorted(range(3), key=lambda a: matrices[a].shape[0] / volume.shape[a])
    for axis in order:
        current = _apply_along(current, matrices[axis], axis)
    return current


def _apply_along(volume: np.ndarray, matrix: np.ndarray, axis: int) -> np.ndarray:
    n0, n1, n2 = volume.shape
    if axis == 0:
        return (matrix @ volume.reshape(n0, n1 * n2)).reshape(matrix.shape[0], n1, n2)
    if axis == 2:
        return (volume.reshape(n0 * n1, n2) @ matrix.T).reshape(n0, n1, matrix.shape[0])
    out = np.empty((n0, matrix.shape[0], n2), dtype=np.float32)
    for i in range(n0):  # one (m1 × n1)·(n1 × n2) product per slab, no transposed copies
        np.matmul(matrix, volume[i], out=out[i])
    return out
