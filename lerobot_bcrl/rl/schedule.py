"""theta_t, the weight of the BC term in `L = theta_t * L_BC + (1 - theta_t) * L_PPO` (method.md section 4).

Schedules are functions of the optimisation step; the counters are saved with every checkpoint so that a resumed
run continues the same theta_t.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

SCHEDULE_TYPES = ("auto", "three_phase", "step", "constant")


@dataclass
class ScheduleConfig:
    # auto: three_phase when fine-tuning a BC checkpoint, constant 0 (pure PPO) from scratch (bcrl-finetune).
    # three_phase: 1 before alpha, exp(-(t - alpha) / beta) until phi, 0 after (the paper's schedule).
    # step: 1 until step_start, then x step_factor every step_every optimisation steps (its step variant).
    # constant: theta_t = constant_theta always (1 = pure BC, 0 = pure PPO).
    type: str = "auto"
    alpha: int = 0  # optimisation steps of pure BC before the decay starts
    beta: float = 2000.0  # decay time constant, in optimisation steps
    phi: int = 10_000  # optimisation step from which theta_t = 0 (pure PPO)
    step_start: int = 10_000  # step variant: first decay
    step_every: int = 100  # step variant: decay period, in optimisation steps
    step_factor: float = 0.97  # step variant: multiplier per period
    constant_theta: float = 0.0  # constant schedule's value
    # Floor of the decaying schedules (three_phase, step): theta_t = max(theta_t, theta_min). 0 is the
    # paper (pure PPO after phi); > 0 keeps a BC anchor for good (docs/RESULTS.md: pure PPO collapsed here).
    theta_min: float = 0.0

    def __post_init__(self):
        if self.type not in SCHEDULE_TYPES:
            raise ValueError(f"schedule.type must be one of {SCHEDULE_TYPES}, got {self.type!r}")
        if self.type == "three_phase" and not (0 <= self.alpha <= self.phi and self.beta > 0):
            raise ValueError("three_phase needs 0 <= alpha <= phi and beta > 0")
        if not 0.0 <= self.theta_min <= 1.0:
            raise ValueError(f"schedule.theta_min must be in [0, 1], got {self.theta_min}")


    @property
    def floor(self) -> float:
        """The floor theta_t actually has: theta_min, except for the constant schedule (its own value)."""
        return 0.0 if self.type == "constant" else self.theta_min


def theta_at(cfg: ScheduleConfig, optim_step: int) -> float:
    """theta_t in [0, 1] after `optim_step` optimisation steps."""
    if cfg.type == "constant":
        return cfg.constant_theta
    return max(_decaying_theta(cfg, optim_step), cfg.floor)


def _decaying_theta(cfg: ScheduleConfig, optim_step: int) -> float:
    if cfg.type == "three_phase":
        if optim_step < cfg.alpha:
            return 1.0
        if optim_step >= cfg.phi:
            return 0.0
        return math.exp(-(optim_step - cfg.alpha) / cfg.beta)
    if cfg.type == "step":
        if optim_step < cfg.step_start:
            return 1.0
        n_decays = (optim_step - cfg.step_start) // cfg.step_every  # 1 at step_start, x factor 100 steps on
        return cfg.step_factor**n_decays
    raise ValueError(f"schedule type {cfg.type!r} has no value until it is resolved (bcrl-finetune resolves 'auto')")


@dataclass
class ScheduleState:
    """The counters a checkpoint stores: optimisation steps (theta_t's clock) and PPO iterations (worker seeds)."""

    optim_step: int = 0
    ppo_iteration: int = 0

    def theta(self, cfg: ScheduleConfig) -> float:
        return theta_at(cfg, self.optim_step)
