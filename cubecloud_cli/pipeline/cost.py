"""What a `detail` run will cost, said before its long stages start: the wall time and peak memory
measured on the 2-core CPU VM (docs/results.md, "The scan's own detail"), interpolated to the
cube's size along the fitted power law between the nearest measured sizes."""

from __future__ import annotations

import math

# size -> (seconds from the scan to the report, peak memory in GB): `bench/scaling.py` on the
# chest CT with `--preset detail`, both splat runs included, numba's first compilation included
# (docs/results.md, "The scan's own detail": the scaling table, run S).
MEASURED_DETAIL: dict[int, tuple[float, float]] = {
    128: (231.0, 0.67),
    192: (243.0, 0.82),
    256: (331.0, 1.17),
    384: (533.0, 2.46),
    512: (967.0, 4.74),
}


def power_law(size: float, points: dict[int, float]) -> float:
    """``points`` (size -> value) read at ``size`` on straight lines in log-log between the two
    nearest measured sizes, and along the end segments' slopes beyond them."""
    sizes = sorted(s for s, v in points.items() if s > 0 and v > 0)
    if not sizes or not (size > 0 and math.isfinite(size)):
        return math.nan
    if len(sizes) == 1:
        return points[sizes[0]]
    below = max([s for s in sizes[:-1] if s <= size], default=sizes[0])
    above = sizes[sizes.index(below) + 1]
    slope = math.log(points[above] / points[below]) / math.log(above / below)
    return points[below] * (size / below) ** slope


def expected_cost(size: int, measured: dict[int, tuple[float, float]] = MEASURED_DETAIL) -> tuple[float, float] | None:
    """(seconds, GB) a detail run of a size³ cube took on a 2-core CPU, or None where nothing is measured."""
    if not measured:
        return None
    seconds = power_law(size, {s: v[0] for s, v in measured.items()})
    memory = power_law(size, {s: v[1] for s, v in measured.items()})
    return seconds, memory


def describe_cost(size: int, measured: dict[int, tuple[float, float]] = MEASURED_DETAIL) -> str | None:
    """One line for the log, or None."""
    cost = expected_cost(size, measured)
    if cost is None or not all(math.isfinite(v) for v in cost):
        return None
    seconds, memory = cost
    return (
        f"a {size}³ detail run takes about {seconds / 60:.0f} min and {memory:.1f} GB on a 2-core CPU "
        f"(as measured on the chest CT from 128³ to 512³; more cores or a GPU take less)"
    )
