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
from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig
from lerobot_bcrl.rl.ppo import FinetuneConfig, set_critic

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
SIGMAS = ("0", "0.01", "0.1")  # the paper's demonstrators


def parse(cls, path: Path):
    return draccus.parse(cls, config_path=str(path), args=[])


def test_every_config_file_is_covered():
    tested = {f"{kind}_lift_{mode}.json" for kind in ("bc", "bcrl", "ppo_scratch") for mode in ("lowdim", "images")}
    tested |= {f"record_sigma{sigma}.yaml" for sigma in SIGMAS} | {"record_multi_demonstrator.yaml"}
    tested |= {"bcrl_lift_lowdim_best_validation.json", "record_lowdim_retry.yaml"}
    names = {p.name for p in CONFIGS.iterdir() if p.suffix in (".json", ".yaml")}
    assert names == tested, f"configs without a test: {sorted(names - tested)}; tested but missing: {sorted(tested - names)}"


@pytest.mark.parametrize("mode, observation_mode", [("lowdim", "low_dim"), ("images", "pixels")])
def test_bc_configs_load_as_lerobot_train_configs(mode, observation_mode):
    cfg = parse(TrainPipelineConfig, CONFIGS / f"bc_lift_{mode}.json")
    assert cfg.policy.type == "bcrl"
    assert cfg.policy.observation_mode == observation_mode
    assert cfg.policy.push_to_hub is False  # the hub is not reachable by default
    assert cfg.steps > 0 and cfg.batch_size > 0


@pytest.mark.parametrize("mode, obs_type", [("lowdim", "agent_pos"), ("images", "pixels_agent_pos")])
def test_bcrl_and_scratch_configs_load_as_finetune_configs(mode, obs_type):
    bcrl = parse(FinetuneConfig, CONFIGS / f"bcrl_lift_{mode}.json")
    scratch = parse(FinetuneConfig, CONFIGS / f"ppo_scratch_lift_{mode}.json")
    for cfg in (bcrl, scratch):
        assert cfg.env.type == "bcrl_lift" and cfg.env.obs_type == obs_type
        # the goal's budget, as run: training stops after the first whole iteration that reaches total_env_steps
        per_iteration = cfg.rollout.steps_per_iteration
        assert 0 < math.ceil(cfg.total_env_steps / per_iteration) * per_iteration <= 300_000
        assert cfg.final_eval_episodes >= 50  # the report's confidence intervals need >= 50 episodes
    # BC+RL: theta_t = 1 first, then decays to 0 (three phases, alpha < phi)
    assert bcrl.schedule.type == "three_phase" and 0 < bcrl.schedule.alpha < bcrl.schedule.phi
    # the recipe's own critic is in the file (a --policy.* field would be lost to the checkpoint's config)
    assert bcrl.ppo.critic_hidden_dims == (256, 256)
    # PPO from scratch: no BC term at any step
    assert scratch.schedule.type == "constant" and scratch.schedule.constant_theta == 0.0


def test_best_validation_config_is_the_recipe_with_a_floor_a_smaller_std_and_a_chosen_result():
    recipe = draccus.encode(parse(FinetuneConfig, CONFIGS / "bcrl_lift_lowdim.json"))
    cfg = parse(FinetuneConfig, CONFIGS / "bcrl_lift_lowdim_best_validation.json")
    changed = {"schedule.theta_min": cfg.schedule.theta_min, "ppo.reset_log_std": cfg.ppo.reset_log_std,
               "total_env_steps": cfg.total_env_steps, "eval_freq": cfg.eval_freq, "eval_episodes": cfg.eval_episodes,
               "save_freq": cfg.save_freq, "select": cfg.select}
    assert changed == {"schedule.theta_min": 0.2, "ppo.reset_log_std": -2.0, "total_env_steps": 102400,
                       "eval_freq": 12800, "eval_episodes": 20, "save_freq": 25600, "select": "best_validation"}
    encoded = draccus.encode(cfg)
    for dotted in changed:  # nothing else differs from the recipe
        *parents, leaf = dotted.split(".")
        target, source = encoded, recipe
        for key in parents:
            target, source = target[key], source[key]
        target[leaf] = source[leaf]
    encoded.pop("output_dir"), recipe.pop("output_dir")
    assert encoded == recipe
    # whole iterations: the evaluations (the candidates) fall on iteration ends, the last at the budget
    per_iteration = cfg.rollout.steps_per_iteration
    assert cfg.eval_freq % per_iteration == 0 and cfg.total_env_steps % cfg.eval_freq == 0


def test_the_configs_critic_goes_onto_the_policy_or_is_refused():
    # the demo keeps the value on the policy's trunk: an empty list parses as "no separate critic"
    cfg = draccus.parse(FinetuneConfig, config_path=str(CONFIGS / "bcrl_lift_lowdim.json"),
                        args=["--ppo.critic_hidden_dims=[]", "--policy.type=bcrl"])
    assert cfg.ppo.critic_hidden_dims == ()
    bc_policy = BCRLConfig()  # a BC checkpoint's config: no critic of its own
    set_critic(bc_policy, None)
    assert bc_policy.critic_hidden_dims == ()
    set_critic(bc_policy, [256, 256])
    assert bc_policy.critic_hidden_dims == (256, 256)
    set_critic(bc_policy, (256, 256))  # a fine-tuned checkpoint with the same critic goes on
    with pytest.raises(ValueError, match=r"critic_hidden_dims=\[64\].*critic_hidden_dims=\[256, 256\]"):
        set_critic(bc_policy, (64,))


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
