"""theta_t at the boundaries of every schedule, and the schedule state that checkpoints carry."""

from __future__ import annotations

import math

import pytest

from lerobot_bcrl.rl.schedule import ScheduleConfig, ScheduleState, theta_at


def test_three_phase_boundaries():
    cfg = ScheduleConfig(type="three_phase", alpha=100, beta=50.0, phi=300)
    assert theta_at(cfg, 0) == 1.0
    assert theta_at(cfg, 99) == 1.0
    assert theta_at(cfg, 100) == pytest.approx(1.0)  # exp(0): continuous where the decay starts
    assert theta_at(cfg, 150) == pytest.approx(math.exp(-1))
    assert theta_at(cfg, 299) == pytest.approx(math.exp(-199 / 50))
    assert theta_at(cfg, 300) == 0.0
    assert theta_at(cfg, 10**9) == 0.0
    values = [theta_at(cfg, t) for t in range(0, 400, 7)]
    assert all(a >= b for a, b in zip(values, values[1:]))  # never increases


def test_step_variant_decays_by_factor_every_period_after_start():
    cfg = ScheduleConfig(type="step", step_start=10_000, step_every=100, step_factor=0.97)
    assert theta_at(cfg, 9_999) == 1.0
    assert theta_at(cfg, 10_000) == 1.0
    assert theta_at(cfg, 10_099) == 1.0
    assert theta_at(cfg, 10_100) == pytest.approx(0.97)
    assert theta_at(cfg, 10_250) == pytest.approx(0.97**2)
    assert theta_at(cfg, 20_000) == pytest.approx(0.97**100)


def test_constant():
    assert theta_at(ScheduleConfig(type="constant", constant_theta=0.3), 12345) == 0.3


def test_theta_min_floors_the_decaying_schedules_only():
    three_phase = ScheduleConfig(type="three_phase", alpha=100, beta=50.0, phi=300, theta_min=0.2)
    assert theta_at(three_phase, 0) == 1.0
    assert theta_at(three_phase, 150) == pytest.approx(math.exp(-1))  # above the floor: untouched
    assert theta_at(three_phase, 181) == pytest.approx(0.2)  # exp(-81/50) = 0.198 < 0.2
    assert theta_at(three_phase, 300) == 0.2 and theta_at(three_phase, 10**9) == 0.2  # after phi: the floor, not 0
    step = ScheduleConfig(type="step", step_start=0, step_every=1, step_factor=0.5, theta_min=0.1)
    assert theta_at(step, 1) == 0.5 and theta_at(step, 50) == 0.1
    assert theta_at(ScheduleConfig(type="constant", constant_theta=0.0, theta_min=0.3), 5) == 0.0
    with pytest.raises(ValueError):
        ScheduleConfig(type="three_phase", theta_min=1.5)


def test_invalid_schedules_are_refused():
    with pytest.raises(ValueError):
        ScheduleConfig(type="linear")
    with pytest.raises(ValueError):
        ScheduleConfig(type="three_phase", alpha=10, phi=5)


def test_state_gives_theta_from_its_counters():
    cfg = ScheduleConfig(type="three_phase", alpha=0, beta=10.0, phi=100)
    state = ScheduleState(optim_step=20, ppo_iteration=2)
    assert state.theta(cfg) == pytest.approx(math.exp(-2))


def test_run_label_names_the_method_the_floor_and_the_kl_stop(tmp_path):
    import json
    from pathlib import Path

    from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig
    from lerobot_bcrl.rl.configuration import FinetuneConfig

    cfg = FinetuneConfig(policy=BCRLConfig(), output_dir=Path("unused"), total_env_steps=1000)
    assert cfg.method == "PPO from scratch"
    cfg.policy.pretrained_path = Path("bc/pretrained_model")
    assert cfg.method == "BC+RL"
    cfg.schedule = ScheduleConfig(type="three_phase", alpha=10, beta=5.0, phi=20, theta_min=0.2)
    assert cfg.method == "BC+RL, theta_t >= 0.2"
    cfg.ppo.target_kl = 0.1
    assert cfg.method == "BC+RL, theta_t >= 0.2, KL stop 0.1"
    cfg.total_env_steps = 0
    assert cfg.method == "BC"
    # evaluating a checkpoint bcrl-finetune trained for 192k env steps: BC+RL, whatever the schedule flags say
    state_dir = tmp_path / "000192000" / "training_state"
    state_dir.mkdir(parents=True)
    (state_dir / "training_step.json").write_text(json.dumps({"env_steps": 192000}))
    cfg.policy.pretrained_path = tmp_path / "000192000" / "pretrained_model"
    assert cfg.method == "BC+RL"
