"""Small statistics shared by summaries, evaluations and reports: means with 95 % confidence intervals."""

from __future__ import annotations

import math

import numpy as np


def mean_ci95(values) -> tuple[float, float]:
    """(mean, half-width of the normal-approximation 95 % CI); the CI is NaN below two values."""
    array = np.asarray(list(values), dtype=float)
    if len(array) < 2:
        return (float(array.mean()) if len(array) else float("nan")), float("nan")
    return float(array.mean()), float(1.96 * array.std(ddof=1) / math.sqrt(len(array)))
