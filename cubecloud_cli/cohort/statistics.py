"""Paired statistics over a cohort: Cube-Cloud against random initialisation, scan by scan.

The scans are the unit: each contributes one paired difference d = Cube-Cloud − random of its
headline score. Reported: the mean difference, a percentile-bootstrap 95 % interval of that mean,
the two-sided Wilcoxon signed-rank p-value (exact for small cohorts without ties, the normal
approximation with the tie correction otherwise, as scipy.stats.wilcoxon does by default) and
how many scans each method wins.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

# Up to this many non-zero differences without ties the signed-rank distribution is enumerated.
EXACT_LIMIT = 50
BOOTSTRAP_RESAMPLES = 10_000


@dataclass(frozen=True)
class PairedSummary:
    scans: int  # pairs with both scores finite
    mean_difference: float
    ci_low: float
    ci_high: float
    wilcoxon_p: float
    wins: int  # scans where the first method scores higher
    losses: int
    ties: int

    def as_dict(self) -> dict:
        return asdict(self)


def finite_pairs(first, second) -> tuple[np.ndarray, np.ndarray]:
    """The pairs where both scores are finite (a failed or missing run drops its scan)."""
    a, b = np.asarray(first, dtype=np.float64), np.asarray(second, dtype=np.float64)
    keep = np.isfinite(a) & np.isfinite(b)
    return a[keep], b[keep]


def middle_value(values: np.ndarray) -> float:
    """An element at the middle of the sorted values: the centre that sums are taken about, so
    that huge values of one size cannot overflow (a median of two of them would)."""
    return float(np.sort(values)[values.size // 2])


def mean_std(values) -> tuple[float, float]:
    """Mean and sample standard deviation (n − 1) of the finite values; NaN where undefined."""
    finite = np.asarray(values, dtype=np.float64)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        return math.nan, math.nan
    centre = middle_value(finite)
    offsets = finite - centre
    return centre + float(offsets.mean()), float(offsets.std(ddof=1)) if finite.size > 1 else math.nan


def bootstrap_mean_interval(
    differences, confidence: float = 0.95, resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0
) -> tuple[float, float]:
    """Percentile-bootstrap interval of the mean of the finite differences: scans resampled with
    replacement. The means are taken about a middle value, so that huge equal values cannot overflow."""
    d = np.asarray(differences, dtype=np.float64)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return math.nan, math.nan
    centre = middle_value(d)
    rng = np.random.default_rng(seed)
    means = centre + (d - centre)[rng.integers(0, d.size, size=(resamples, d.size))].mean(axis=1)
    tail = (1.0 - confidence) / 2.0
    low, high = np.quantile(means, [tail, 1.0 - tail])
    return float(low), float(high)


def average_ranks(values: np.ndarray) -> np.ndarray:
    """Ranks 1..n, tied values sharing the mean of their ranks."""
    order = np.argsort(values, kind="stable")
    ranks = np.empty(values.size, dtype=np.float64)
    sorted_values = values[order]
    start = 0
    while start < values.size:
        end = start
        while end + 1 < values.size and sorted_values[end + 1] == sorted_values[start]:
            end += 1
        ranks[order[start : end + 1]] = (start + end) / 2.0 + 1.0
        start = end + 1
    return ranks


def signed_rank_null_counts(n: int) -> np.ndarray:
    """How many of the 2ⁿ sign patterns give each W⁺ = 0 … n(n+1)/2 (ranks 1..n, no ties)."""
    counts = np.zeros(n * (n + 1) // 2 + 1, dtype=np.float64)
    counts[0] = 1.0
    for rank in range(1, n + 1):
        counts[rank:] = counts[rank:] + counts[:-rank].copy()
    return counts


def wilcoxon_signed_rank_p(differences) -> float:
    """Two-sided p-value of the Wilcoxon signed-rank test that the differences centre on 0.

    Zero differences are dropped (Wilcoxon's convention). 1.0 when none remain."""
    d = np.asarray(differences, dtype=np.float64)
    d = d[np.isfinite(d) & (d != 0.0)]
    n = d.size
    if n == 0:
        return 1.0
    ranks = average_ranks(np.abs(d))
    w_plus = float(ranks[d > 0].sum())
    _, tie_sizes = np.unique(np.abs(d), return_counts=True)
    if n <= EXACT_LIMIT and np.all(tie_sizes == 1):
        counts = signed_rank_null_counts(n)
        total = counts.sum()
        w = int(round(w_plus))
        below, above = counts[: w + 1].sum() / total, counts[w:].sum() / total
        return float(min(1.0, 2.0 * min(below, above)))
    mean = n * (n + 1) / 4.0
    variance = n * (n + 1) * (2 * n + 1) / 24.0 - float(np.sum(tie_sizes**3 - tie_sizes)) / 48.0
    if variance <= 0.0:
        return 1.0
    z = (w_plus - mean) / math.sqrt(variance)
    return float(math.erfc(abs(z) / math.sqrt(2.0)))


def paired_summary(first, second, seed: int = 0) -> PairedSummary:
    """The paired comparison of two methods' per-scan scores (``first`` − ``second``)."""
    a, b = finite_pairs(first, second)
    d = a - b
    low, high = bootstrap_mean_interval(d, seed=seed)
    return PairedSummary(
        scans=int(d.size),
        mean_difference=mean_std(d)[0],
        ci_low=low,
        ci_high=high,
        wilcoxon_p=wilcoxon_signed_rank_p(d),
        wins=int(np.sum(d > 0)),
        losses=int(np.sum(d < 0)),
        ties=int(np.sum(d == 0)),
    )
