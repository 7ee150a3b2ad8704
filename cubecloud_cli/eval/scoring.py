"""Per-view scores of docs/design.md §5 and their mean ± std: the numbers of `cubecloud eval`.

Every view is scored on its own (PSNR, SSIM and MSE over the whole image, and again over the
foreground, where the reference is non-zero), then the views are summarised. Known answers stay
answers, not errors: identical images give PSNR = +inf, a view with no foreground gets NaN for
its foreground scores and is left out of their mean (``*_views`` says how many counted).
"""

from __future__ import annotations

import math

import numpy as np

from cubecloud_cli.numerics.metrics import SSIM_RADIUS, mse, psnr_from_mse, ssim_and_masked

METRICS = ("psnr", "ssim", "mse", "psnr_foreground", "ssim_foreground", "mse_foreground")


def as_grey_stack(images: np.ndarray) -> np.ndarray:
    """(N, H, W) float32 from (N, H, W) or (N, H, W, C): colour is averaged to grey, because the
    references are grey renders of a CT."""
    images = np.asarray(images, dtype=np.float32)
    if images.ndim == 4:
        images = images.mean(axis=-1)
    if images.ndim != 3:
        raise ValueError(f"need a stack of images (N, H, W[, C]), got shape {images.shape}")
    return images


def score_view(reference: np.ndarray, estimate: np.ndarray) -> dict[str, float]:
    """The six scores of one (H, W) view. SSIM needs 11×11 pixels; smaller views get NaN."""
    foreground = reference > 0
    has_foreground = bool(foreground.any())
    whole, inside = mse(reference, estimate), mse(reference, estimate, foreground) if has_foreground else math.nan
    scores = {
        "psnr": psnr_from_mse(whole),
        "mse": whole,
        "psnr_foreground": psnr_from_mse(inside),
        "mse_foreground": inside,
        "ssim": math.nan,
        "ssim_foreground": math.nan,
    }
    if min(reference.shape) >= 2 * SSIM_RADIUS + 1:
        # No foreground: the masked mean is NaN, as the default above.
        scores["ssim"], scores["ssim_foreground"] = ssim_and_masked(reference, estimate, foreground)
    return scores


def score_views(reference: np.ndarray, estimate: np.ndarray) -> list[dict[str, float]]:
    reference, estimate = as_grey_stack(reference), as_grey_stack(estimate)
    if reference.shape != estimate.shape:
        raise ValueError(f"reference and estimate stacks differ: {reference.shape} vs {estimate.shape}")
    return [score_view(r, e) for r, e in zip(reference, estimate)]


def summarize(rows: list[dict[str, float]]) -> dict[str, float | int]:
    """Mean and (population) standard deviation of each score over the views that have it.

    An infinite PSNR (a view reproduced exactly) makes the mean +inf and its std NaN, which is
    the honest summary; NaN views (no foreground, too small for SSIM) are not counted."""
    summary: dict[str, float | int] = {"views": len(rows)}
    for metric in METRICS:
        values = np.array([row[metric] for row in rows], dtype=np.float64)
        values = values[~np.isnan(values)]
        summary[f"{metric}_views"] = int(values.size)
        if values.size == 0:
            summary[metric], summary[f"{metric}_std"] = math.nan, math.nan
        elif np.isinf(values).any():
            summary[metric] = (
                float(values.mean()) if not (np.isposinf(values).any() and np.isneginf(values).any()) else math.nan
            )
            summary[f"{metric}_std"] = math.nan
        else:
            summary[metric], summary[f"{metric}_std"] = float(values.mean()), float(values.std())
    return summary
