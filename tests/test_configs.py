"""Every ready config in configs/ loads with the parser of the command the docs give for it (draccus refuses an
unknown or misspelt field), and holds the method's invariants: a BC+RL run decays theta_t, PPO from scratch has
no BC term, the low-dim and image variants read the observations their names say."""

from __future__ import annotations

import math
from pathlib import Path

import draccus
import pytest
from lerobot.configs.train import TrainPipelineConfig

import lerobot_bcrl  # noqa: F401  (registers the bcrl policy and env types)
from dataset_tools.record import RecordConfig
from lerobot_bcrl.rl.configuration import FinetuneConfig

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
SIGMAS = ("0", "0.01", "0.1")  # the paper's demonstrators
BCRL_CONFIGS = {"bcrl_lift_lowdim_best_validation.json": "agent_pos", "bcrl_lift_images.json": "pixels_agent_pos"}


def parse(cls, path: Path):
    return draccus.parse(cls, config_path=str(path), args=[])


def test_every_config_file_is_covered():
    tested = {f"{kind}_lift_{mode}.json" for kind in ("bc", "ppo_scratch") for mode in ("lowdim", "images")}
    tested |= {f"record_sigma{sigma}.yaml" for sigma in SIGMAS} | {"record_multi_demonstrator.yaml"}
    tested |= set(BCRL_CONFIGS) | {"record_lowdim_retry.yaml", "record_operator_mix.yaml"}
    tested |= {"record_weak_expert.yaml"}  # tests/test_experiments_script.py records it with a tiny weak expert
    tested |= {"record_lab_bags.yaml", "bc_lab_images.json"}
    names = {p.name for p in CONFIGS.iterdir() if p.suffix in (".json", ".yaml")}
    assert names == tested, f"configs without a test: {sorted(names - tested)}; tested but missing: {sorted(tested - names)}"


@pytest.mark.parametrize("mode, observation_mode", [("lowdim", "low_dim"), ("images", "pixels")])
def test_bc_configs_load_as_lerobot_train_configs(mode, observation_mode):
    cfg = parse(TrainPipelineConfig, CONFIGS / f"bc_lift_{mode}.json")
    assert cfg.policy.type == "bcrl"
    assert cfg.policy.observation_mode == observation_mode
    assert cfg.policy.push_to_hub is False  # the hub is not reachable by default
    assert cfg.steps > 0 and cfg.batch_size > 0
    # BC+RL's critic comes with the BC checkpoint: bcrl-finetune takes the policy's config from it
    assert cfg.policy.critic_hidden_dims == (256, 256)


def test_lab_configs_record_through_the_command_path_and_train_on_images():
    from dataset_tools.make_demo_bags import MakeDemoBagsConfig

    record = draccus.parse(MakeDemoBagsConfig, config_path=str(CONFIGS / "record_lab_bags.yaml"), args=["--urdf=sawyer.urdf"])
    record.check()
    assert record.drive == "command_path" and record.control_fps == 30 and record.formats == ["ros1"]
    assert record.n_episodes == 30 and record.control_steps / record.control_fps >= 5  # ~30 demos, as in the paper
    assert 0 < record.operator.speed < 1 and record.operator.noise_std > 0  # slower than the expert, and a drifting hand
    train = parse(TrainPipelineConfig, CONFIGS / "bc_lab_images.json")
    assert train.policy.type == "bcrl" and train.policy.observation_mode == "pixels" and train.policy.push_to_hub is False
    assert train.dataset.repo_id == "local/lab_towel"  # what scripts/lab_loop.sh converts the bags into


@pytest.mark.parametrize("name", sorted(BCRL_CONFIGS))
def test_bcrl_configs_load_as_finetune_configs_and_decay_theta_from_one(name):
    cfg = parse(FinetuneConfig, CONFIGS / name)
    assert cfg.env.type == "bcrl_lift" and cfg.env.obs_type == BCRL_CONFIGS[name]
    per_iteration = cfg.rollout.steps_per_iteration  # training stops after the first whole iteration at the budget
    assert 0 < math.ceil(cfg.total_env_steps / per_iteration) * per_iteration <= 300_000  # the goal's budget
    assert cfg.schedule.type == "three_phase" and 0 < cfg.schedule.alpha < cfg.schedule.phi  # theta_t = 1, then decays
    if cfg.select == "best_validation":  # the candidates fall on iteration ends, the last at the budget
        assert cfg.eval_freq % per_iteration == 0 and cfg.total_env_steps % cfg.eval_freq == 0


@pytest.mark.parametrize("mode, obs_type", [("lowdim", "agent_pos"), ("images", "pixels_agent_pos")])
def test_scratch_configs_have_no_bc_term(mode, obs_type):
    cfg = parse(FinetuneConfig, CONFIGS / f"ppo_scratch_lift_{mode}.json")
    assert cfg.env.obs_type == obs_type and cfg.final_eval_episodes >= 50
    assert cfg.schedule.type == "constant" and cfg.schedule.constant_theta == 0.0


def test_the_recipe_config_chooses_on_validation_decays_theta_to_zero_and_colors_its_noise():
    cfg = parse(FinetuneConfig, CONFIGS / "bcrl_lift_lowdim_best_validation.json")
    assert cfg.select == "best_validation" and cfg.schedule.theta_min == 0.0
    assert cfg.ppo.term_weighting == "gradient_share" and cfg.final_eval_episodes >= 50
    assert cfg.eval_episodes >= 20
    assert cfg.rollout.noise_color_beta > 0  # white noise only where a command says --rollout.noise_color_beta=0


@pytest.mark.parametrize("sigma", SIGMAS)
def test_record_configs_are_the_papers_demonstrators(sigma):
    cfg = parse(RecordConfig, CONFIGS / f"record_sigma{sigma}.yaml")
    assert cfg.sigma == float(sigma) and not cfg.demonstrators
    assert cfg.n_episodes > 0 and cfg.repo_id.endswith(f"sigma{sigma}")


def test_multi_demonstrator_config_has_several_demonstrators():
    cfg = parse(RecordConfig, CONFIGS / "record_multi_demonstrator.yaml")
    noise = [(d.noise_std, d.noise_mean, d.noise_correlation) for d in cfg.demonstrators]
    assert len(noise) >= 2 and len(set(noise)) == len(noise)  # distinct demonstrators


def test_retry_record_config_is_the_recipes_demonstrations_at_any_sigma():
    cfg = draccus.parse(RecordConfig, config_path=str(CONFIGS / "record_lowdim_retry.yaml"), args=["--sigma=0.01"])
    assert cfg.sigma == 0.01 and not cfg.demonstrators and cfg.expert == "scripted"
    assert cfg.images is False and cfg.n_episodes == 100 and cfg.seed == 0
    assert cfg.miss_probability == 0.3 and cfg.reopen_on_empty_grasp is True
    assert tuple(cfg.miss_height_range_m) == (0.015, 0.045) and cfg.miss_max_aside_m == 0.035


def test_operator_mix_config_is_six_skilled_operators_with_unlabelled_mistakes():
    cfg = parse(RecordConfig, CONFIGS / "record_operator_mix.yaml")
    assert len(cfg.demonstrators) == 6 and all(d.has_skill for d in cfg.demonstrators)
    assert cfg.n_episodes == 120 and cfg.images is False and cfg.miss_probability == 0.0
    assert cfg.expert == "scripted" and cfg.seed == 0
