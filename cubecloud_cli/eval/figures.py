"""The pictures of the eval report: error grids with a colour bar (PNG), turntables (GIF) and line
plots (SVG). Drawn with Pillow (already installed with imageio) and plain SVG text, so the
report needs no plotting library."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import escape

import imageio.v3 as iio
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from cubecloud_cli.core.writes import write_bytes

# A perceptually ordered map from black through purple and orange to pale yellow (the anchor
# colours of matplotlib's "inferno"), so error magnitude reads as brightness even in grey print.
ERROR_COLOURS = np.array([(0, 0, 4), (87, 16, 110), (188, 55, 84), (249, 142, 9), (252, 255, 164)], dtype=np.float64)
PANEL_MIN_PIXELS = 192  # small renders are enlarged (nearest neighbour) so a reader can see pixels
LABEL_HEIGHT = 16
BACKGROUND = (255, 255, 255)
TEXT = (20, 20, 20)
SERIES_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#17becf", "#7f7f7f")


def colour_map(values: np.ndarray, vmax: float) -> np.ndarray:
    """(…, 3) uint8 colours of ``values`` scaled to [0, vmax] (clipped; NaN shows as black)."""
    return np.round(anchor_colours(np.asarray(values, dtype=np.float64) / max(vmax, 1e-12), ERROR_COLOURS)).astype(
        np.uint8
    )


def anchor_colours(fractions: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """(…, 3) float64 colours interpolated linearly between ``anchors`` spaced evenly over [0, 1],
    at ``fractions`` (clipped to [0, 1]; NaN as 0)."""
    anchors = np.asarray(anchors, dtype=np.float64)
    position = np.clip(np.nan_to_num(np.asarray(fractions, dtype=np.float64)), 0.0, 1.0) * (len(anchors) - 1)
    low = np.minimum(position.astype(np.int64), len(anchors) - 2)
    weight = (position - low)[..., None]
    return anchors[low] * (1.0 - weight) + anchors[low + 1] * weight


def grey_to_rgb(image: np.ndarray) -> np.ndarray:
    grey = np.round(np.clip(np.nan_to_num(np.asarray(image, dtype=np.float64)), 0.0, 1.0) * 255.0).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=-1)


def enlargement(shape: tuple[int, ...]) -> int:
    """The whole factor a panel of ``shape`` (H, W, …) is enlarged by, so a reader can see pixels."""
    return max(1, math.ceil(PANEL_MIN_PIXELS / max(shape[:2])))


def _enlarge(image: np.ndarray) -> Image.Image:
    picture = Image.fromarray(image)
    factor = enlargement(image.shape)
    return picture.resize((picture.width * factor, picture.height * factor), Image.NEAREST) if factor > 1 else picture


def error_scale(reference: np.ndarray, estimates: list[np.ndarray]) -> float:
    """One colour-bar maximum for a view: the 99.5th percentile of every method's |error|, so a
    few extreme pixels do not wash out the rest (values above it show at full colour)."""
    errors = np.concatenate([np.abs(e - reference).ravel() for e in estimates]) if estimates else np.zeros(1)
    return float(max(np.percentile(errors, 99.5), 1e-3))


def _colour_bar(height: int, vmax: float, font) -> Image.Image:
    bar_width, text_width = 14, 56
    gradient = colour_map(np.linspace(vmax, 0.0, height)[:, None].repeat(bar_width, axis=1), vmax)
    bar = Image.new("RGB", (bar_width + text_width, height + LABEL_HEIGHT), BACKGROUND)
    bar.paste(Image.fromarray(gradient), (0, LABEL_HEIGHT))
    draw = ImageDraw.Draw(bar)
    draw.text((0, 2), "|error|", fill=TEXT, font=font)
    draw.text((bar_width + 3, LABEL_HEIGHT), f"{vmax:.3g}", fill=TEXT, font=font)
    draw.text((bar_width + 3, LABEL_HEIGHT + height // 2 - 5), f"{vmax / 2:.3g}", fill=TEXT, font=font)
    draw.text((bar_width + 3, LABEL_HEIGHT + height - 10), "0", fill=TEXT, font=font)
    return bar


def error_grid(reference: np.ndarray, renders: dict[str, np.ndarray], title: str) -> Image.Image:
    """One row per method: reference | render | |render − reference| colour-mapped, with one
    colour bar for the whole grid (shared scale, so rows compare)."""
    font = ImageFont.load_default()
    vmax = error_scale(reference, list(renders.values()))
    panel = _enlarge(grey_to_rgb(reference))
    width, height = panel.size
    bar = _colour_bar(height, vmax, font)
    grid = Image.new(
        "RGB", (3 * width + bar.width + 8, LABEL_HEIGHT + len(renders) * (height + LABEL_HEIGHT)), BACKGROUND
    )
    draw = ImageDraw.Draw(grid)
    draw.text((2, 2), title, fill=TEXT, font=font)
    for row, (name, render) in enumerate(renders.items()):
        top = LABEL_HEIGHT + row * (height + LABEL_HEIGHT)
        for column, (label, image) in enumerate(
            (
                ("reference", grey_to_rgb(reference)),
                (name, grey_to_rgb(render)),
                (f"|{name} - reference|", colour_map(np.abs(render - reference), vmax)),
            )
        ):
            draw.text((column * width + 2, top + 2), label, fill=TEXT, font=font)
            grid.paste(_enlarge(image), (column * width, top + LABEL_HEIGHT))
        grid.paste(bar, (3 * width + 6, top))
    return grid


def write_turntable(path: Path, frames: np.ndarray, seconds: float = 6.0) -> None:
    """A looping GIF of (N, H, W) grey frames in [0, 1], one full turn in ``seconds``."""
    frames = np.stack([grey_to_rgb(frame) for frame in frames])
    duration = max(20, int(1000 * seconds / max(len(frames), 1)))
    write_bytes(path, iio.imwrite("<bytes>", frames, extension=".gif", duration=duration, loop=0))


def _nice_ticks(low: float, high: float, count: int = 5) -> list[float]:
    if not (math.isfinite(low) and math.isfinite(high)) or high <= low:
        high = low + 1.0 if math.isfinite(low) else 1.0
        low = high - 1.0
    raw = (high - low) / count
    magnitude = 10 ** math.floor(math.log10(raw))
    step = next(m * magnitude for m in (1, 2, 2.5, 5, 10) if m * magnitude >= raw)
    first = math.ceil(low / step) * step
    return [first + i * step for i in range(int((high - first) / step + 1e-9) + 1)]


def _log_ticks(low: float, high: float) -> list[float]:
    """Ticks for an axis drawn in log10 units from ``low`` to ``high``: the exponents of the
    1-2-5 values in between (only the powers of ten when those are enough), so labels read in
    the data's own units (10 s, 100 s) rather than as logarithms."""
    if not (math.isfinite(low) and math.isfinite(high)) or high <= low:
        return _nice_ticks(low, high)
    decades = range(math.floor(low), math.ceil(high) + 1)
    powers = [float(k) for k in decades if low <= k <= high]
    if len(powers) >= 3:
        return powers[:: math.ceil(len(powers) / 8)]  # a label every few decades on a wide range
    steps = [k + math.log10(m) for k in decades for m in (1, 2, 5)]
    ticks = [t for t in steps if low <= t <= high]
    return ticks if len(ticks) >= 2 else _nice_ticks(low, high)


def _tick_label(value: float, log: bool) -> str:
    """A tick's label in data units; three significant digits with thousands separators (1,000
    rather than 1e+03) on a log axis."""
    if not log:
        return f"{value:g}"
    if abs(value) > 300:  # 10**value would overflow a float (or lose every digit): say the power
        return f"1e{round(value):+d}"
    return f"{float(f'{10.0**value:.3g}'):,g}"


def _to_axis(values: list[float], log: bool) -> list[float]:
    """Values in the axis's drawing units: unchanged, or log10 with non-positive values left out
    (NaN) since they have no place on a log axis."""
    if not log:
        return [float(v) for v in values]
    return [math.log10(v) if math.isfinite(v) and v > 0 else math.nan for v in map(float, values)]


Box = tuple[float, float, float, float]  # left, top, right, bottom, in SVG pixels
LABEL_FONT_PX = 10
# Sans-serif glyphs average a bit over half an em; an estimate that errs wide keeps labels apart.
LABEL_CHAR_WIDTH = 0.62 * LABEL_FONT_PX


def _overlaps(a: Box, b: Box) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def place_labels(
    anchors: list[tuple[float, float]], texts: list[str], bounds: Box, marker_radius: float = 3.5
) -> list[tuple[float, float, str, Box] | None]:
    """Where each non-empty label goes beside its point: ``(x, y, text-anchor, box)``, or None when
    no spot is free. Labels are placed greedily, each at the first of a fixed list of spots
    around its point (right, left, above, below, then further out) whose box stays inside
    ``bounds`` and clear of every label placed before and of every marker."""
    markers = [(x - marker_radius, y - marker_radius, x + marker_radius, y + marker_radius) for x, y in anchors]
    placed: list[Box] = []
    spots = [(6, -5), (6, 9), (-6, -5), (-6, 9), (0, -8), (0, 16)]
    spots += [(dx, dy) for step in (14, 24, 34, 44) for dx in (6, -6) for dy in (-step - 5, step + 9)]
    result: list[tuple[float, float, str, Box] | None] = []
    for (x, y), text in zip(anchors, texts):
        if not text:
            result.append(None)
            continue
        width = LABEL_CHAR_WIDTH * len(text)
        choice = None
        for dx, dy in spots:
            anchor = "start" if dx > 0 else "end" if dx < 0 else "middle"
            tx, ty = x + dx, y + dy
            left = tx if anchor == "start" else tx - width if anchor == "end" else tx - width / 2
            box = (left, ty - LABEL_FONT_PX, left + width, ty + 2)
            inside = bounds[0] <= box[0] and box[2] <= bounds[2] and bounds[1] <= box[1] and box[3] <= bounds[3]
            if inside and not any(_overlaps(box, other) for other in placed + markers):
                choice = (tx, ty, anchor, box)
                break
        if choice is not None:
            placed.append(choice[3])
        result.append(choice)
    return result


def _padded_range(values: list[float]) -> tuple[float, float]:
    """The data's range widened by 5% on each side, so no point sits on an axis or the frame."""
    low, high = min(values), max(values)
    pad = 0.05 * (high - low) if high > low else 0.5
    return low - pad, high + pad


@dataclass(frozen=True)
class _PlotArea:
    """Where a plot's data range lands on its canvas: margins in pixels, the axes' data range."""

    width: int
    height: int
    left: int
    right: int
    top: int
    bottom: int
    x_range: tuple[float, float]
    y_range: tuple[float, float]

    def sx(self, x: float) -> float:
        x0, x1 = self.x_range
        return self.left + (x - x0) / (x1 - x0) * (self.width - self.left - self.right)

    def sy(self, y: float) -> float:
        y0, y1 = self.y_range
        return self.height - self.bottom - (y - y0) / (y1 - y0) * (self.height - self.top - self.bottom)


def line_plot_svg(
    series: list[tuple[str, list[float], list[float]]],
    title: str,
    x_label: str,
    y_label: str,
    markers_only: bool = False,
    point_labels: dict[str, list[str]] | None = None,
    size: tuple[int, int] = (640, 400),
    y_include: tuple[float, ...] = (),
    log_axes: tuple[bool, bool] = (False, False),
    x_ticks: tuple[float, ...] = (),
) -> str:
    """An SVG plot of ``(label, xs, ys)`` series: lines (or points), axes with ticks, a legend.
    Non-finite points are left out. ``point_labels`` names points of a series; a name is drawn
    where it overlaps no other name or point, further out with a leader line when it must, and
    left out when the plot has no free spot for it. The y range always spans ``y_include`` (a
    reference such as 0). ``log_axes`` draws x and/or y on a log scale, labelled in the data's
    units; ``x_ticks`` (data units) replaces the chosen x ticks, for example the sizes measured."""
    log_x, log_y = log_axes
    series = [(label, _to_axis(xs, log_x), _to_axis(ys, log_y)) for label, xs, ys in series]
    y_include = tuple(_to_axis(list(y_include), log_y))
    points = [(x, y) for _, xs, ys in series for x, y in zip(xs, ys) if math.isfinite(x) and math.isfinite(y)]
    xs_all, ys_all = [p[0] for p in points] or [0.0, 1.0], ([p[1] for p in points] or [0.0, 1.0]) + list(y_include)
    (x_low, x_high), (y_low, y_high) = _padded_range(xs_all), _padded_range(ys_all)
    given_x = sorted(t for t in _to_axis(list(x_ticks), log_x) if math.isfinite(t))
    x_positions = given_x or (_log_ticks if log_x else _nice_ticks)(x_low, x_high)
    y_positions = (_log_ticks if log_y else _nice_ticks)(y_low, y_high)
    x0, x1 = min(x_positions[0], x_low), max(x_positions[-1], x_high)
    y0, y1 = min(y_positions[0], y_low), max(y_positions[-1], y_high)
    x1, y1 = (x1 if x1 > x0 else x0 + 1.0), (y1 if y1 > y0 else y0 + 1.0)
    area = _PlotArea(*size, left=70, right=170, top=40, bottom=50, x_range=(x0, x1), y_range=(y0, y1))
    parts = _frame_svg(area, title, (x_label, y_label), (x_positions, y_positions), log_axes)
    series_parts, anchors, texts = _series_svg(area, series, markers_only, point_labels or {})
    bounds = (area.left + 1, area.top - 10, area.width - area.right + 4, area.height - area.bottom - 1)
    return "\n".join([*parts, *series_parts, *_point_labels_svg(anchors, texts, bounds), "</svg>"])


def _frame_svg(
    area: _PlotArea,
    title: str,
    labels: tuple[str, str],
    ticks: tuple[list[float], list[float]],
    log_axes: tuple[bool, bool],
) -> list[str]:
    """The canvas, title, axes, ticks (x below, y with a grid line) and the axis labels."""
    width, height, left, right, top, bottom = area.width, area.height, area.left, area.right, area.top, area.bottom
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-family="sans-serif" font-size="12">',
        f'<rect width="{width}" height="{height}" fill="white"/>',
        f'<text x="{width / 2 - right / 2:.0f}" y="22" text-anchor="middle" font-size="14">{escape(title)}</text>',
        f'<line x1="{left}" y1="{height - bottom}" x2="{width - right}" y2="{height - bottom}" stroke="black"/>',
        f'<line x1="{left}" y1="{top}" x2="{left}" y2="{height - bottom}" stroke="black"/>',
    ]
    for x in ticks[0]:
        sx = area.sx(x)
        parts.append(
            f'<line x1="{sx:.1f}" y1="{height - bottom}" x2="{sx:.1f}" y2="{height - bottom + 5}" stroke="black"/>'
            f'<text x="{sx:.1f}" y="{height - bottom + 18}" text-anchor="middle">{_tick_label(x, log_axes[0])}</text>'
        )
    for y in ticks[1]:
        sy = area.sy(y)
        parts.append(
            f'<line x1="{left - 5}" y1="{sy:.1f}" x2="{width - right}" y2="{sy:.1f}" stroke="#e5e5e5"/>'
            f'<text x="{left - 8}" y="{sy + 4:.1f}" text-anchor="end">{_tick_label(y, log_axes[1])}</text>'
        )
    parts.append(
        f'<text x="{(left + width - right) / 2:.0f}" y="{height - 12}" text-anchor="middle">{escape(labels[0])}</text>'
        f'<text transform="translate(18 {(top + height - bottom) / 2:.0f}) rotate(-90)" text-anchor="middle">{escape(labels[1])}</text>'
    )
    return parts


def _series_svg(
    area: _PlotArea,
    series: list[tuple[str, list[float], list[float]]],
    markers_only: bool,
    point_labels: dict[str, list[str]],
) -> tuple[list[str], list[tuple[float, float, str]], list[str]]:
    """Each series' line, points and legend entry; and every drawn point's pixel position and
    colour with the name ``point_labels`` gives it ("" for none), for the labels to place."""
    parts, anchors, texts = [], [], []
    for index, (label, xs, ys) in enumerate(series):
        colour = SERIES_COLOURS[index % len(SERIES_COLOURS)]
        kept = [(area.sx(x), area.sy(y)) for x, y in zip(xs, ys) if math.isfinite(x) and math.isfinite(y)]
        if len(kept) > 1 and not markers_only:
            path = " ".join(f"{x:.1f},{y:.1f}" for x, y in kept)
            parts.append(f'<polyline points="{path}" fill="none" stroke="{colour}" stroke-width="2"/>')
        names = point_labels.get(label, [])
        for i, (x, y) in enumerate(kept):
            parts.append(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="3.5" fill="{colour}"/>')
            anchors.append((x, y, colour))
            texts.append(names[i] if i < len(names) else "")
        legend_x, legend_y = area.width - area.right, area.top + 10 + 18 * index
        parts.append(
            f'<rect x="{legend_x + 12}" y="{legend_y - 9}" width="12" height="12" fill="{colour}"/>'
            f'<text x="{legend_x + 30}" y="{legend_y + 1}">{escape(label)}</text>'
        )
    return parts, anchors, texts


def _point_labels_svg(
    anchors: list[tuple[float, float, str]], texts: list[str], bounds: tuple[float, float, float, float]
) -> list[str]:
    """The points' names where ``place_labels`` finds room, with a leader line to a name moved
    out of its point's reach."""
    parts = []
    for (x, y, colour), text, spot in zip(anchors, texts, place_labels([(x, y) for x, y, _ in anchors], texts, bounds)):
        if spot is None:
            continue
        tx, ty, anchor, box = spot
        near_x, near_y = min(max(x, box[0]), box[2]), min(max(y, box[1]), box[3])
        if math.hypot(near_x - x, near_y - y) > 8:
            parts.append(
                f'<line x1="{x:.1f}" y1="{y:.1f}" x2="{near_x:.1f}" y2="{near_y:.1f}" stroke="{colour}" '
                'stroke-width="0.7" opacity="0.6"/>'
            )
        parts.append(
            f'<text x="{tx:.1f}" y="{ty:.1f}" font-size="{LABEL_FONT_PX}" text-anchor="{anchor}" '
            f'fill="{colour}">{escape(text)}</text>'
        )
    return parts
