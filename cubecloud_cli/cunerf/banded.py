"""The grid start's per-axis operators (cunerf/grid_init.py), applied along one axis of an n³ array
in O(n³) time and a block at a time.

Each is a banded n×n matrix: a linear interpolation reads two neighbouring vertices per output
vertex, and the preconditioner (MᵀM + λI)⁻¹Mᵀ of a mean of such reads is a banded product followed
by a banded solve. Applied as dense n×n products (``volume.resample_axes``), they cost O(n⁴): the
fit of a 512³ CT took 451 s. The arithmetic runs as torch operations on views of the arrays (one
fused pass each, where numpy needs two to five); the solve's transposing copies run in numpy,
which makes them several times faster than torch does.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from scipy.linalg import cholesky_banded

# A render's block: small enough that its temporaries stay in cache (and off the peak memory),
# large enough that the per-call overhead is paid on a million elements.
BLOCK_ELEMENTS = 1 << 20
# A solve's block (float64, 64 MB): its substitutions make 2·n·bandwidth calls on rows of
# K = this / n columns, which pay for the calls' overhead from K ≈ 16384 on.
SOLVE_ELEMENTS = 1 << 23


class Taps(NamedTuple):
    """Linear interpolation of ``m`` wanted coordinates: row i is
    ``w_lower[i]·known[lower[i]] + w_upper[i]·known[upper[i]]``."""

    lower: np.ndarray  # int64 (m,)
    upper: np.ndarray  # int64 (m,)
    w_lower: np.ndarray  # float32 (m,): the interpolation matrix's entries, rounded alike
    w_upper: np.ndarray  # float32 (m,)


class Run(NamedTuple):
    """Output rows start … stop − 1 of a read: row start + k reads rows lower + step·k and
    upper + step·k (step 0 holds a border row) with the same two weights."""

    start: int
    stop: int
    lower: int
    upper: int
    step: int
    w_lower: float
    w_upper: float


class BandedInverse(NamedTuple):
    """(MᵀM + λI)⁻¹Mᵀ of one axis: Mᵀ as its nonzero diagonals (d, Mᵀ[j, j + d] over j, as a
    float64 column), and MᵀM + λI = L·D·Lᵀ with L unit lower triangular: ``below[k − 1][j]`` =
    L[j, j − k] (Python floats: each is one substitution step's scalar)."""

    transposed: tuple[tuple[int, torch.Tensor], ...]
    below: tuple[list[float], ...]
    inverse_diagonal: torch.Tensor  # 1 / D, a float64 column


def interpolation_taps(known: np.ndarray, wanted: np.ndarray) -> Taps:
    """The two taps per wanted coordinate of linear interpolation from the sorted coordinates
    ``known``, held at the border value beyond the outermost one."""
    known, wanted = np.asarray(known, dtype=np.float64), np.asarray(wanted, dtype=np.float64)
    if known.size == 1:
        zero = np.zeros(wanted.size, dtype=np.int64)
        return Taps(zero, zero, np.ones(wanted.size, dtype=np.float32), np.zeros(wanted.size, dtype=np.float32))
    upper = np.clip(np.searchsorted(known, wanted), 1, known.size - 1)
    lower = upper - 1
    span = known[upper] - known[lower]
    # Clipped before the division: a far coordinate over a subnormal span would overflow.
    reach = np.clip(wanted - known[lower], 0.0, span)
    fraction = np.divide(reach, span, out=np.zeros_like(reach), where=span > 0)
    return Taps(lower, upper, (1.0 - fraction).astype(np.float32), fraction.astype(np.float32))


def taps_matrix(taps: Taps, columns: int) -> np.ndarray:
    """The dense (m, columns) float32 matrix of ``taps``."""
    matrix = np.zeros((taps.lower.size, columns), dtype=np.float32)
    rows = np.arange(taps.lower.size)
    matrix[rows, taps.lower] = taps.w_lower
    matrix[rows, taps.upper] += taps.w_upper
    return matrix


def tap_runs(taps: Taps) -> tuple[Run, ...]:
    """``taps`` as runs of rows that read sliding (or fixed) rows with equal weights: a read at
    a constant shift is three runs (the held border rows on each side and the interior)."""
    lower, upper = taps.lower.tolist(), taps.upper.tolist()
    w_lower, w_upper = taps.w_lower.tolist(), taps.w_upper.tolist()
    runs: list[Run] = []
    start, step = 0, None  # step: the run's stride, None while it has one row
    for row in range(1, len(lower) + 1):
        if row < len(lower):
            stride = lower[row] - lower[row - 1]
            weights_alike = (w_lower[row], w_upper[row]) == (w_lower[start], w_upper[start])
            alike = weights_alike and upper[row] - upper[row - 1] == stride
            if alike and stride in (0, 1) and step in (None, stride):
                step = stride
                continue
        runs.append(
            Run(start, row, lower[start], upper[start], 1 if step is None else step, w_lower[start], w_upper[start])
        )
        start, step = row, None
    return tuple(runs)


def read_along(source: torch.Tensor, runs: tuple[Run, ...], axis: int, out: torch.Tensor, first: int = 0) -> None:
    """Rows first … first + out.shape[axis] − 1 of the read ``runs`` along ``axis`` of
    ``source``, into ``out``, by slicing: no index arrays, no dense product."""
    count = out.shape[axis]
    for run in runs:
        start, stop = max(run.start, first), min(run.stop, first + count)
        if start >= stop:
            continue
        offset = (start - run.start) * run.step
        length = (stop - start - 1) * run.step + 1  # one held row broadcasts over the run
        target = out.narrow(axis, start - first, stop - start)
        lower = source.narrow(axis, run.lower + offset, length).expand_as(target)
        upper = source.narrow(axis, run.upper + offset, length).expand_as(target)
        if run.w_lower == 0 or run.w_upper == 0:  # a border row, held: a weight of 1 (or w) on one tap
            held, weight = (upper, run.w_upper) if run.w_lower == 0 else (lower, run.w_lower)
            target.copy_(held)
            if weight != 1:
                target.mul_(weight)
        else:  # lower + w·(upper − lower): the matrix's two taps, to float32 rounding
            torch.lerp(lower, upper, run.w_upper, out=target)


def banded_inverse(matrix: np.ndarray, damping: float) -> BandedInverse:
    """The banded pieces of (MᵀM + λI)⁻¹Mᵀ for a banded square ``matrix`` M (float64)."""
    size = matrix.shape[0]
    rows, columns = np.nonzero(matrix)
    offsets = rows - columns  # d = row − column: Mᵀ[j, j + d] = M[j + d, j]
    below, above = (int(offsets.max()), int(offsets.min())) if offsets.size else (0, 0)
    transposed = tuple(
        (d, torch.from_numpy(np.diagonal(matrix, -d)[:, None].copy()))
        for d in range(above, below + 1)
        if np.any(np.diagonal(matrix, -d))
    )
    gram = matrix.T @ matrix + damping * np.eye(size)
    width = min(below - above, size - 1)  # MᵀM's bandwidth
    banded = np.zeros((width + 1, size))
    for k in range(width + 1):
        banded[width - k, k:] = np.diagonal(gram, k)
    factor = cholesky_banded(banded, check_finite=False)  # factor[width − k, j] = U[j − k, j], UᵀU = gram
    pivots = factor[width]
    # L = Uᵀ·diag(U)⁻¹ and D = diag(U)²: L[j, j − k] = U[j − k, j] / U[j − k, j − k].
    lower = tuple([0.0] * k + (factor[width - k, k:] / pivots[: size - k]).tolist() for k in range(1, width + 1))
    return BandedInverse(transposed, lower, torch.from_numpy(1.0 / pivots[:, None] ** 2))


def _transpose_apply(values: torch.Tensor, inverse: BandedInverse, out: torch.Tensor) -> None:
    """out = Mᵀ·values along axis 0 of (n, K) arrays, one diagonal (one fused pass) at a time."""
    size = values.shape[0]
    main = dict(inverse.transposed).get(0)
    if main is None:
        out.zero_()
    else:  # the main diagonal covers every row: it starts the sum
        torch.mul(values, main, out=out)
    for d, diagonal in inverse.transposed:
        if d > 0:
            out[: size - d].addcmul_(values[d:], diagonal)
        elif d < 0:
            out[-d:].addcmul_(values[: size + d], diagonal)


def _substitute(values: torch.Tensor, inverse: BandedInverse) -> None:
    """values ← (L·D·Lᵀ)⁻¹·values along axis 0 of (n, K), in place. The substitutions run down
    the n rows, each step on all K columns at once: LAPACK's banded solve runs down one column
    at a time, latency-bound, and was five times slower here."""
    rows = values.unbind(0)
    for row in range(1, len(rows)):  # L·y = values
        for k, coefficients in enumerate(inverse.below[:row], start=1):
            rows[row].sub_(rows[row - k], alpha=coefficients[row])
    values.mul_(inverse.inverse_diagonal)  # D·z = y
    for row in range(len(rows) - 2, -1, -1):  # Lᵀ·x = z
        for k, coefficients in enumerate(inverse.below[: len(rows) - 1 - row], start=1):
            rows[row].sub_(rows[row + k], alpha=coefficients[row + k])


def solve_along(array: np.ndarray, inverse: BandedInverse, axis: int) -> None:
    """Apply (MᵀM + λI)⁻¹Mᵀ along ``axis`` of the 3D ``array``, in place, a block at a time in
    float64 (with λ = 1e-3 the Gram matrix's condition number reaches 1e3). The blocks reuse
    two buffers (a fresh array per block costs more in page faults than the solve), filled and
    emptied by numpy, whose transposing copies are the faster."""
    moved = np.moveaxis(array, axis, 0)  # the solved axis first: a block's columns
    size, count = moved.shape[0], max(1, SOLVE_ELEMENTS // (moved.shape[0] * moved.shape[2]))
    buffers = np.empty((2, size * min(count, moved.shape[1]) * moved.shape[2]))
    for start in range(0, moved.shape[1], count):
        block = moved[:, start : start + count]
        # A prefix of a flat buffer: always a view, whatever the width of the last block.
        values, solved = (buffer[: block.size].reshape(size, -1) for buffer in buffers)
        values.reshape(block.shape)[...] = block
        _transpose_apply(torch.from_numpy(values), inverse, torch.from_numpy(solved))
        _substitute(torch.from_numpy(solved), inverse)
        block[...] = solved.reshape(block.shape)


class RenderPlan(NamedTuple):
    """A render's reads: per axis, each shift's runs; and the shifts as x → y → [(z, weight)], so
    a read along x (and then y) is shared by every shift that has it."""

    runs: tuple[dict[float, tuple[Run, ...]], ...]
    tree: dict[float, dict[float, list[tuple[float, float]]]]


def render_plan(resolution: int, shifts: np.ndarray, weights: np.ndarray) -> RenderPlan:
    """The plan of Σᵢ wᵢ·sigmoid(f read at vertex + shiftᵢ) on an r³ grid; shifts (N, 3) in vertices."""
    vertices = np.arange(resolution, dtype=np.float64)
    runs = tuple(
        {s: tap_runs(interpolation_taps(vertices, vertices + s)) for s in np.unique(shifts[:, axis]).tolist()}
        for axis in range(3)
    )
    tree: dict[float, dict[float, list[tuple[float, float]]]] = {}
    for (sx, sy, sz), weight in zip(shifts.tolist(), weights.tolist()):
        # The weight rounded to float32, as the dense render applied it.
        tree.setdefault(sx, {}).setdefault(sy, []).append((sz, float(np.float32(weight))))
    return RenderPlan(runs, tree)


def preconditioner(resolution: int, shifts: np.ndarray, weights: np.ndarray, damping: float) -> list[BandedInverse]:
    """Per axis, the damped inverse of the shifts' reads averaged by their share of the weight."""
    vertices = np.arange(resolution, dtype=np.float64)
    total = max(float(weights.sum()), 1e-12)
    inverses = []
    for axis in range(3):
        mean = np.zeros((resolution, resolution))
        for s in np.unique(shifts[:, axis]):
            read = taps_matrix(interpolation_taps(vertices, vertices + s), resolution)  # r² floats, not r⁴ work
            mean += weights[shifts[:, axis] == s].sum() / total * read
        inverses.append(banded_inverse(mean, damping))
    return inverses


def _render_block(logits: torch.Tensor, plan: RenderPlan, first: int, out: torch.Tensor, scratch: torch.Tensor) -> None:
    """Rows first … first + len(out) − 1 (along x) of the render of ``logits`` into ``out``;
    ``scratch`` holds three blocks of out's shape or more."""
    x_read, y_read, z_read = (buffer[: out.shape[0]] for buffer in scratch)
    started = False  # the first sample's term is written, not added to zeros: one pass fewer
    for sx, by_y in plan.tree.items():
        read_along(logits, plan.runs[0][sx], 0, x_read, first)
        for sy, by_z in by_y.items():
            read_along(x_read, plan.runs[1][sy], 1, y_read)
            for sz, weight in by_z:
                read_along(y_read, plan.runs[2][sz], 2, z_read)
                if started:
                    out.add_(z_read.sigmoid_(), alpha=weight)
                else:
                    torch.mul(z_read.sigmoid_(), weight, out=out)
                    started = True
    if not started:
        out.zero_()


def render(logits: torch.Tensor, plan: RenderPlan, target: torch.Tensor, out: torch.Tensor) -> float:
    """Render ``logits`` (r³ float32) into ``out`` a block of x-rows at a time (the reads'
    temporaries stay block-sized) and return the root-mean-square error against ``target``."""
    rows = max(1, BLOCK_ELEMENTS // (logits.shape[1] * logits.shape[2]))
    scratch = torch.empty((3, min(rows, logits.shape[0]), *logits.shape[1:]), dtype=logits.dtype)
    squares = 0.0
    for first in range(0, logits.shape[0], rows):
        block = out[first : first + rows]
        _render_block(logits, plan, first, block, scratch)
        difference = torch.sub(target[first : first + rows], block, out=scratch[0, : block.shape[0]])
        squares += float(difference.square_().sum(dtype=torch.float64))
    return float(np.sqrt(squares / max(logits.numel(), 1)))
