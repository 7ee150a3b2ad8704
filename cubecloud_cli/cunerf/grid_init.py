"""A grid field that starts where training would take thousands of iterations to get: at the
volume it is fitted to (``--grid-init volume``).

The MLP passes the finest level's first feature through unchanged (relu(f) − relu(−f) = f) with a
constant density high enough that a cube's weights sum past 1, so the bounded render is a fixed
weighted mean of its samples' sigmoid(f). That feature is then solved for, so that the cube
render at each vertex equals the training volume there: the samples sit off the vertex (a
quarter voxel for the CPU presets), and logit(intensity) at the vertices alone would render the
volume blurred (32 dB instead of 63 on the training voxels of the bundled CT). The solve is
Newton's method on the logits, each step inverting the render's linear part (a separable
interpolation per axis, inverted once per axis, with a little Tikhonov damping where a cube's
samples cannot tell a vertex from its neighbours). Every per-axis operator is banded and applied
as such (cunerf/banded.py): O(r³) a render or a step. At r = 512 on 2 cores, a CT-like phantom
fits in 34 s and 3.1 GB where dense r×r products took 257 s and 6.1 GB.

The other features, levels and hidden units keep their random start and join in as training
moves them. Only training voxels are read: held-out slices (and, with --train-scale, every voxel
off the training lattice) are filled by linear interpolation between them, so validation still
scores what the field learned rather than what it was given.
"""

from __future__ import annotations

import numpy as np
import torch

from cubecloud_cli.cunerf.banded import (
    BLOCK_ELEMENTS,
    Taps,
    interpolation_taps,
    preconditioner,
    render,
    render_plan,
    solve_along,
    taps_matrix,
)
from cubecloud_cli.cunerf.config import RenderConfig
from cubecloud_cli.cunerf.fields import GridField
from cubecloud_cli.cunerf.model import CubeModel
from cubecloud_cli.cunerf.rendering import render_cubes
from cubecloud_cli.cunerf.sampling import cube_offsets
from cubecloud_cli.cunerf.supervision import TrainingVoxels

# Intensities are clipped to [ε, 1 − ε] before the logit, which is then finite (±6.9) and within
# reach of Adam's steps; sigmoid(±6.9) differs from 0 and 1 by 1e-3, below one grey level.
LOGIT_EPSILON = 1e-3
# softplus(3) ≈ 3.05: with 2³ samples on one shell the weights then sum to about 4, so the
# bounded render divides by them and returns the mean intensity (cunerf/rendering.py).
INITIAL_DENSITY_RAW = 3.0
# The solve stops when every vertex renders within this many logits of its target (1e-3 of
# intensity at most), or after FIT_STEPS steps; each step costs one render of the grid.
FIT_TOLERANCE = 4e-3
FIT_STEPS = 8
# Tikhonov damping of each axis's inverse: a cube of half-size one voxel averages v−1, v, v+1 as
# ¼ ½ ¼ and cannot render a checkerboard at all; the damping caps the gain at 1/(2√λ) ≈ 16.
INVERSE_DAMPING = 1e-3
# Solved logits are held within ±LOGIT_LIMIT, where sigmoid is still exact in float32.
LOGIT_LIMIT = 30.0


def logit(values: np.ndarray, epsilon: float = LOGIT_EPSILON) -> np.ndarray:
    """log(p / (1 − p)) of values clipped to [ε, 1 − ε]; NaN becomes ε."""
    values = np.asarray(values)
    dtype = values.dtype if np.issubdtype(values.dtype, np.floating) else np.float64
    return _logit_(torch.from_numpy(np.array(values, dtype=dtype)), epsilon).numpy()


def _logit_(values: torch.Tensor, epsilon: float = LOGIT_EPSILON) -> torch.Tensor:
    """logit, in place: one fused pass per step and no temporary (numpy's log1p is five times
    slower than torch's log, and each numpy step is a pass of its own)."""
    return values.nan_to_num_(nan=epsilon).clamp_(epsilon, 1.0 - epsilon).logit_()


def linear_interpolation_matrix(known: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """The (len(wanted), len(known)) matrix of linear interpolation from values at the sorted
    coordinates ``known`` (spaced at will: a held-out slice is a wider gap) to ``wanted``, held
    at the border value beyond the outermost known coordinate. Rows are convex weights; the
    grid start applies the same two taps per row (banded.interpolation_taps) without the matrix."""
    return taps_matrix(interpolation_taps(known, wanted), np.size(known))


def training_volume_at(voxels: TrainingVoxels, resolution: int) -> np.ndarray:
    """The training voxels' intensities, interpolated to the vertices of an r³ grid level
    (vertex v at the centre of voxel v of an r³ volume over the same cube)."""
    lattice = voxels.lattice.cpu().numpy()
    slices = voxels.slices.cpu().numpy()
    volume = voxels.volume.cpu().numpy()
    # Vertex v of the level lies at voxel index (v + ½)·S/r − ½ of the S³ volume.
    vertices = (np.arange(resolution) + 0.5) * (voxels.size / resolution) - 0.5
    x, y, z = (_volume_taps(axis, vertices) for axis in (lattice, lattice, slices))
    out = np.empty((resolution,) * 3, dtype=np.float32)
    # One output slab at a time, from the two volume slabs it reads: two taps per axis, O(r³)
    # in all (one dense matrix per axis would be O(r⁴) and a full copy of the training voxels).
    for row in range(resolution):
        plane = volume[x.lower[row]] * x.w_lower[row] + volume[x.upper[row]] * x.w_upper[row]
        lines = plane[y.lower] * y.w_lower[:, None] + plane[y.upper] * y.w_upper[:, None]
        out[row] = lines[:, z.lower] * z.w_lower + lines[:, z.upper] * z.w_upper
    return out


def _volume_taps(known: np.ndarray, wanted: np.ndarray) -> Taps:
    """Taps from the training coordinates ``known`` whose indices are the volume's own."""
    taps = interpolation_taps(known, wanted)
    return taps._replace(lower=known[taps.lower], upper=known[taps.upper])


def sample_weights(render: RenderConfig) -> tuple[np.ndarray, np.ndarray]:
    """A test render's sample offsets (N, 3), world units, and the weights (N,) that make the
    render Σ wᵢ·intensityᵢ when every sample has the start's density."""
    offsets = cube_offsets(1, render.samples_per_axis, "lattice", render.cube_half_size)
    count = offsets.shape[1]
    density = torch.nn.functional.softplus(torch.full((1, count), INITIAL_DENSITY_RAW))
    rendered = render_cubes(offsets, torch.ones(1, count), density, render.half_diagonal)
    weights = torch.zeros(count).scatter(0, rendered.order[0], rendered.weights[0])
    weights = weights / rendered.weights.sum().clamp(min=1.0)  # the bounded render's division
    return offsets[0].double().numpy(), weights.double().numpy()


def shifted_interpolation(resolution: int, shift: float) -> np.ndarray:
    """The (r, r) matrix that reads a level's vertices ``shift`` vertices off each vertex."""
    vertices = np.arange(resolution, dtype=np.float64)
    return linear_interpolation_matrix(vertices, vertices + shift)


def damped_inverse(matrix: np.ndarray, damping: float = INVERSE_DAMPING) -> np.ndarray:
    """(MᵀM + λI)⁻¹Mᵀ: M⁻¹ where M is well conditioned, bounded where it is not. (The solve
    applies it in banded form: banded.banded_inverse.)"""
    gram = matrix.T @ matrix + damping * np.eye(matrix.shape[1])
    return np.linalg.solve(gram, matrix.T)


def _logit_error(target: torch.Tensor, rendered: torch.Tensor) -> float:
    """logit(target) − logit(rendered), written over ``rendered`` a block at a time; returns its
    largest magnitude."""
    rows = max(1, BLOCK_ELEMENTS // (rendered.shape[1] * rendered.shape[2]))
    goal = torch.empty((min(rows, rendered.shape[0]), *rendered.shape[1:]), dtype=rendered.dtype)
    largest = 0.0
    for first in range(0, rendered.shape[0], rows):
        block = rendered[first : first + rows]
        block_goal = _logit_(goal[: block.shape[0]].copy_(target[first : first + rows]))
        torch.sub(block_goal, _logit_(block), out=block)
        largest = max(largest, float(block.abs().max()) if block.numel() else 0.0)
    return largest


def fit_vertex_logits(
    target: np.ndarray, shifts: np.ndarray, weights: np.ndarray, steps: int = FIT_STEPS
) -> tuple[np.ndarray, float]:
    """Logits ``f`` on an r³ vertex grid whose render Σᵢ wᵢ·sigmoid(f read at vertex + shiftᵢ)
    matches ``target`` (intensities, r³) at every vertex; ``shifts`` (N, 3) are in vertices.
    Returns the logits and the root-mean-square intensity error that remains."""
    intensities = torch.from_numpy(np.ascontiguousarray(target, dtype=np.float32))
    plan = render_plan(intensities.shape[0], shifts, weights)
    inverses = preconditioner(intensities.shape[0], shifts, weights, INVERSE_DAMPING)
    # Four r³ arrays besides the target: the logits, their render, and a trial of each.
    logits = _logit_(intensities.clone())
    rendered = torch.empty_like(logits)
    cost = render(logits, plan, intensities, rendered)
    trial, trial_rendered = torch.empty_like(logits), torch.empty_like(logits)
    # A step is taken only where it lowers the intensity error, halved up to three times: where no
    # field of this render can hold the volume (a checkerboard under a ¼ ½ ¼ average), the full
    # step overshoots in logits and would make the start worse than no solve.
    for _ in range(steps):
        if _logit_error(intensities, rendered) < FIT_TOLERANCE:
            break
        direction = rendered  # the render is not needed past its error: solved in place
        for axis, inverse in enumerate(inverses):
            solve_along(direction.numpy(), inverse, axis)
        for scale in (1.0, 0.5, 0.25, 0.125):
            torch.mul(direction, scale, out=trial).add_(logits).clamp_(-LOGIT_LIMIT, LOGIT_LIMIT)
            trial_cost = render(trial, plan, intensities, trial_rendered)
            if trial_cost < cost:
                logits, trial = trial, logits
                rendered, trial_rendered = trial_rendered, direction
                cost = trial_cost
                break
        else:
            break
    return logits.numpy(), cost


@torch.no_grad()
def initialise_from_volume(model: CubeModel, voxels: TrainingVoxels) -> float | None:
    """Set the coarse field of ``model`` (in place) to render the training volume before any step.
    Returns the solve's remaining root-mean-square intensity error, or None where there is no solve (a
    fine pass resamples the cube, so its render is not a fixed mean: the logits then start at
    the intensities' own)."""
    field = model.coarse
    if not isinstance(field, GridField):
        raise ValueError("a volume start needs a grid field")
    config = field.config
    if config.hidden < 2:
        raise ValueError("a volume start needs at least 2 hidden units to pass a feature through")
    finest = len(config.resolutions) - 1
    resolution = config.resolutions[finest]
    start = int(field.offsets[finest])
    target = training_volume_at(voxels, resolution)
    remaining = None
    if model.render_config.importance > 0:
        values = logit(target)
    else:
        offsets, weights = sample_weights(model.render_config)
        values, remaining = fit_vertex_logits(target, offsets * resolution / 2.0, weights)  # world → vertices
    # x-major, as the table's rows
    field.table[start : start + resolution**3, 0] = torch.as_tensor(values.reshape(-1), dtype=field.table.dtype)
    first, last = field.mlp[0], field.mlp[2]
    source = finest * config.features  # the finest level's first feature in the MLP's input
    first.weight[:2] = 0.0
    first.weight[0, source], first.weight[1, source] = 1.0, -1.0
    first.bias[:2] = 0.0
    last.weight.zero_()
    last.weight[0, 0], last.weight[0, 1] = 1.0, -1.0
    last.bias[0], last.bias[1] = 0.0, INITIAL_DENSITY_RAW
    return remaining
