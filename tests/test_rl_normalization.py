"""The running mean/std behind PPO's reward normalisation is exact over every batch it has seen."""

from __future__ import annotations

import numpy as np
import pytest

from lerobot_bcrl.rl.normalization import RunningMeanStd


def test_running_mean_std_matches_numpy_over_all_batches():
    rng = np.random.default_rng(0)
    batches = [rng.normal(3.0, 2.0, size=(n, 4)) for n in (7, 50, 1, 300)]
    stats = RunningMeanStd(np.zeros(4), np.ones(4), count=1e-9)  # a negligible prior
    for batch in batches:
        stats.update(batch)
    everything = np.concatenate(batches)
    np.testing.assert_allclose(stats.mean, everything.mean(0), rtol=1e-6)
    np.testing.assert_allclose(stats.var, everything.var(0), rtol=1e-6)
    assert stats.count == pytest.approx(len(everything))
