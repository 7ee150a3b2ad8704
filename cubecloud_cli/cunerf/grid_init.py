"""A grid field that starts where training would take thousands of iterations to get: at the
volume it is fitted to (``--grid-init volume``).

The finest level's first feature is set to logit(intensity) at each vertex, and the MLP to pass
that feature through unchanged (relu(f) − relu(−f) = f) with a constant density high enough that
a cube's weights sum past 1, so the bounded render is the mean of its samples' intensities. The
other features, levels and hidden units keep their random start and join in as training moves
them. Only training voxels are read: held-out slices (and, with --train-scale, every voxel off
the training lattice) are filled by linear interpolation between them, so validation still
scores what the field learned rather than what it was given.
"""

from __future__ import annotations

import numpy as np
import torch

from cubecloud_cli.cunerf.data import TrainingVoxels
from cubecloud_cli.cunerf.fields import GridField
from cubecloud_cli.volume.resample import resample_axes

# Intensities are clipped to [ε, 1 − ε] before the logit, which is then finite (±6.9) and within
# reach of Adam's steps; sigmoid(±6.9) differs from 0 and 1 by 1e-3, below one grey level.
LOGIT_EPSILON = 1e-3
# softplus(3) ≈ 3.05: with 2³ samples on one shell the weights then sum to about 4, so the
# bounded render divides by them and returns the mean intensity (cunerf/rendering.py).
INITIAL_DENSITY_RAW = 3.0


def logit(values: np.ndarray, epsilon: float = LOGIT_EPSILON) -> np.ndarray:
    """log(p / (1 − p)) of values clipped to [ε, 1 − ε]; NaN becomes ε."""
    p = np.clip(np.nan_to_num(values, nan=epsilon), epsilon, 1.0 - epsilon)
    return np.log(p) - np.log1p(-p)


def linear_interpolation_matrix(known: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """The (len(wanted), len(known)) matrix of linear interpolation from values at the sorted
    coordinates ``known`` (spaced at will: a held-out slice is a wider gap) to ``wanted``, held
    at the border value beyond the outermost known coordinate. Rows are convex weights, so
    ``volume.resample_axes`` applies one matrix per axis."""
    known, wanted = np.asarray(known, dtype=np.float64), np.asarray(wanted, dtype=np.float64)
    matrix = np.zeros((wanted.size, known.size), dtype=np.float32)
    if known.size == 1:
        matrix[:, 0] = 1.0
        return matrix
    upper = np.clip(np.searchsorted(known, wanted), 1, known.size - 1)
    lower = upper - 1
    span = known[upper] - known[lower]
    # Clipped before the division: a far coordinate over a subnormal span would overflow.
    reach = np.clip(wanted - known[lower], 0.0, span)
    fraction = np.divide(reach, span, out=np.zeros_like(reach), where=span > 0)
    rows = np.arange(wanted.size)
    matrix[rows, lower] = 1.0 - fraction
    matrix[rows, upper] += fraction
    return matrix


def training_volume_at(voxels: TrainingVoxels, resolution: int) -> np.ndarray:
    """The training voxels' intensities, interpolated to the vertices of an r³ grid level
    (vertex v at the centre of voxel v of an r³ volume over the same cube)."""
    lattice = voxels.lattice.cpu().numpy()
    slices = voxels.slices.cpu().numpy()
    volume = voxels.volume.cpu().numpy()
    known = volume[np.ix_(lattice, lattice, slices)]
    # Vertex v of the level lies at voxel index (v + ½)·S/r − ½ of the S³ volume.
    vertices = (np.arange(resolution) + 0.5) * (voxels.size / resolution) - 0.5
    matrices = [linear_interpolation_matrix(axis, vertices) for axis in (lattice, lattice, slices)]
    return resample_axes(known, matrices)


@torch.no_grad()
def initialise_from_volume(field: GridField, voxels: TrainingVoxels) -> None:
    """Set ``field`` (in place) to render the training volume before any step."""
    config = field.config
    if config.hidden < 2:
        raise ValueError("a volume start needs at least 2 hidden units to pass a feature through")
    finest = len(config.resolutions) - 1
    resolution = config.resolutions[finest]
    start = int(field.offsets[finest])
    values = logit(training_volume_at(voxels, resolution)).reshape(-1)  # x-major, as the table's rows
    field.table[start : start + resolution**3, 0] = torch.as_tensor(values, dtype=field.table.dtype)
    first, last = field.mlp[0], field.mlp[2]
    source = finest * config.features  # the finest level's first feature in the MLP's input
    first.weight[:2] = 0.0
    first.weight[0, source], first.weight[1, source] = 1.0, -1.0
    first.bias[:2] = 0.0
    last.weight.zero_()
    last.weight[0, 0], last.weight[0, 1] = 1.0, -1.0
    last.bias[0], last.bias[1] = 0.0, INITIAL_DENSITY_RAW
