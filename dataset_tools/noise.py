"""Simulated demonstrators: an expert's actions plus seeded noise in controller units, and operator skill.

The paper's demonstrators add i.i.d. Gaussian noise N(0, sigma) to every action. Its future work (and
ours): several demonstrators in one dataset, each with its own bias (noise mean), std and temporal
correlation (an AR(1) process whose stationary std is `noise_std`), and with the skill knobs that real
operators show (slower, hesitant, imprecise, closing too high, giving up), which the scripted expert reads.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class DemonstratorConfig:
    noise_std: float = 0.0  # sigma, in controller units ([-1, 1] per axis)
    noise_mean: float = 0.0  # a constant bias on every axis but the gripper, controller units
    noise_correlation: float = 0.0  # AR(1) coefficient in [0, 1): 0 is the paper's white noise
    # Operator skill (scripted expert only; the defaults are the plain expert). Each grasp attempt draws its
    # own alignment error and early close, from the episode's seeded stream.
    speed: float = 1.0  # factor on the expert's commanded motion (gain and top speed): < 1 is slower
    hesitation_probability: float = 0.0  # per step, chance of starting a pause (zero motion, gripper held)
    hesitation_steps: int = 5  # how long each pause lasts
    grasp_offset_std_m: float = 0.0  # per attempt, Gaussian error of the grasp point in x and y
    yaw_error_std_rad: float = 0.0  # per attempt, Gaussian error of the finger alignment about z
    close_too_high_probability: float = 0.0  # per attempt, chance of closing 3-4.5 cm above the grasp point
    retry_probability: float = 1.0  # after a missed grasp or a drop, chance of trying again (else hover, give up)

    def __post_init__(self):
        if self.noise_std < 0:
            raise ValueError(f"noise_std must be >= 0, got {self.noise_std}")
        if not 0.0 <= self.noise_correlation < 1.0:
            raise ValueError(f"noise_correlation must be in [0, 1), got {self.noise_correlation}")
        if self.speed <= 0 or self.hesitation_steps < 1 or self.grasp_offset_std_m < 0 or self.yaw_error_std_rad < 0:
            raise ValueError("speed must be > 0, hesitation_steps >= 1 and the alignment stds >= 0")
        for name in ("hesitation_probability", "close_too_high_probability", "retry_probability"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")

    @property
    def has_skill(self) -> bool:
        """Whether this operator moves differently from the plain expert (beyond the added noise)."""
        plain = DemonstratorConfig(self.noise_std, self.noise_mean, self.noise_correlation)
        return self != plain


class DemonstratorNoise:
    """One episode's noise sequence for one demonstrator; reproducible from its seed."""

    def __init__(self, demonstrator: DemonstratorConfig, action_dim: int, seed: int | list[int]):
        self.demonstrator = demonstrator
        self._rng = np.random.default_rng(seed)
        self._state = np.zeros(action_dim)
        self._bias = np.full(action_dim, demonstrator.noise_mean)
        self._bias[-1] = 0.0  # a biased gripper would be a different task, not a noisy demonstrator
        self._first = True

    def sample(self) -> np.ndarray:
        d = self.demonstrator
        white = self._rng.normal(0.0, d.noise_std, size=self._state.shape)
        if self._first:
            self._state = white  # start in the stationary distribution
            self._first = False
        else:
            rho = d.noise_correlation
            self._state = rho * self._state + np.sqrt(1.0 - rho**2) * white
        return self._state + self._bias


def beta_demonstrators(
    n: int, max_std: float, a: float = 2.0, b: float = 5.0, max_abs_mean: float = 0.0, seed: int = 0
) -> list[DemonstratorConfig]:
    """`n` operators whose noise std is `max_std * Beta(a, b)` (RoboTurk-like spread of skill)."""
    rng = np.random.default_rng(seed)
    return [
        DemonstratorConfig(
            noise_std=float(max_std * rng.beta(a, b)),
            noise_mean=float(rng.uniform(-max_abs_mean, max_abs_mean)),
            noise_correlation=float(rng.uniform(0.0, 0.9)),
        )
        for _ in range(n)
    ]
