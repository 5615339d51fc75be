"""BC+RL with camera observations (the image configs' path), on the CPU with tiny budgets.

The learner must score the rollout's stored pixels exactly as the worker did when it sampled the actions:
otherwise PPO's ratio is off from the first minibatch. And the whole image pipeline -- a video dataset,
lerobot-train, bcrl-finetune with `pixels_agent_pos` in worker processes, lerobot-eval -- must run.
"""

from __future__ import annotations

import csv
import json
from functools import partial

import numpy as np
import pytest
import torch
from safetensors.torch import load_file
from policy_fixtures import image_dataset_root, lowdim_dataset_root, save_untrained_checkpoint  # noqa: F401
from test_rl_cli import finetune_args, run_cli

from lerobot_bcrl.envs.configuration_lift import GYM_ID
from lerobot_bcrl.rl.agent import BCRLAgent
from lerobot_bcrl.rl.ppo import PPOConfig, select_minibatch, training_batch
from lerobot_bcrl.rl.rollout import ProcessWorkers, make_gym_env


@pytest.mark.parametrize("fixture_name, obs_type", [("lowdim_dataset_root", "agent_pos"),
                                                    ("image_dataset_root", "pixels_agent_pos")])
def test_learner_scores_the_worker_observations_as_the_worker_did(fixture_name, obs_type, request, tmp_path):
    checkpoint = tmp_path / "policy"
    save_untrained_checkpoint(request.getfixturevalue(fixture_name), checkpoint)
    gym_kwargs = {"obs_type": obs_type, "horizon": 4}  # episodes end inside the rollout: resets are covered
    worker_kwargs = [{"make_env": partial(make_gym_env, GYM_ID, gym_kwargs),
                      "make_agent": partial(BCRLAgent.from_pretrained, checkpoint), "n_envs": 2, "seed": 3}]
    learner = BCRLAgent.from_pretrained(checkpoint)
    workers = ProcessWorkers(worker_kwargs)  # a separate process: observations and weights cross a pipe
    try:
        trajectories = workers.collect(learner.state_dict(), 6)
    finally:
        workers.close()

    if obs_type == "pixels_agent_pos":
        pixels = trajectories.observations["pixels.agentview"]
        assert pixels.shape == (6, 2, 128, 128, 3) and pixels.dtype == np.uint8
        assert pixels.std() > 10  # a rendered scene, not a blank frame
    else:
        assert not any(key.startswith("pixels") for key in trajectories.observations)
    batch = training_batch(trajectories, trajectories.rewards, PPOConfig())
    minibatch = select_minibatch(learner, batch, torch.arange(12))
    learner.module.train()  # as in ppo_update
    with torch.no_grad():
        log_prob, _, value = learner.evaluate(minibatch["obs"], minibatch["actions"])
    # float32 sums in other batch shapes differ by ~1e-4; a ratio off by 1e-3 is nothing next to the 0.2 clip
    torch.testing.assert_close(log_prob, minibatch["log_probs"], atol=1e-3, rtol=0)
    value_scale = max(1.0, float(minibatch["values"].abs().max()))
    torch.testing.assert_close(value, minibatch["values"], atol=1e-4 * value_scale, rtol=1e-4)
    # and the check can fail: the neighbouring step's observations under the same actions score differently
    shifted = {key: np.roll(value, 1, axis=0)[:12] for key, value in batch["obs"].items()}
    with torch.no_grad():
        other_log_prob, _, _ = learner.evaluate(learner.observation_batch(shifted), minibatch["actions"])
    assert (other_log_prob - minibatch["log_probs"]).abs().max() > 1e-2


@pytest.mark.slow
def test_bc_plus_rl_on_camera_observations_through_the_real_commands(tmp_path):
    # a video dataset (the default of bcrl-record): the BC term decodes its frames during fine-tuning
    from dataset_tools.record import RecordConfig, record

    data = record(RecordConfig(repo_id="local/camera", root=tmp_path / "camera", n_episodes=1, episode_length=24,
                               sigma=0.1, images=True, video=True))
    assert list((data / "videos").rglob("*.mp4"))
    run_cli("lerobot-train", "--policy.type=bcrl", "--dataset.repo_id=local/camera", f"--dataset.root={data}",
            "--policy.push_to_hub=false", "--steps=2", "--batch_size=4", f"--output_dir={tmp_path / 'bc'}",
            "--num_workers=0", "--policy.device=cpu", "--save_freq=2", "--dataset.video_backend=bcrl_frame_cache")
    bc_checkpoint = tmp_path / "bc" / "checkpoints" / "last" / "pretrained_model"
    assert "observation.images.agentview" in json.loads((bc_checkpoint / "config.json").read_text())["input_features"]
    args = [arg for arg in finetune_args(data, tmp_path / "bcrl", 128) if not arg.startswith("--rollout.n_workers")]
    output = run_cli("bcrl-finetune", f"--policy.path={bc_checkpoint}", *args, "--env.obs_type=pixels_agent_pos",
                     "--rollout.n_workers=1", "--policy.critic_hidden_dims=[32]",
                     "--policy.critic_observation=privileged",  # an asymmetric critic
                     "--dataset.video_backend=bcrl_frame_cache", timeout=300)
    assert "128 env steps" in output
    result = json.loads((tmp_path / "bcrl" / "eval_final.json").read_text())
    assert result["env_steps"] == 128 and result["eval_episodes"] == 1 and 0 < result["theta"] < 1
    (row,) = csv.DictReader((tmp_path / "bcrl" / "logs.csv").open())
    assert int(row["env_steps"]) == 128 and float(row["bc_loss"]) > 0  # the BC term ran on decoded frames
    assert float(row["rendering_s"]) > 0 and float(row["simulation_s"]) > 0  # the camera's time, apart
    pretrained = tmp_path / "bcrl" / "checkpoints" / "last" / "pretrained_model"
    assert json.loads((pretrained / "config.json").read_text())["critic_observation"] == "privileged"
    weights = load_file(pretrained / "model.safetensors")  # the value from the privileged critic, not the actor's
    assert any(name.startswith("model.privileged_critic.") for name in weights)
    assert not any(name.startswith("model.critic.") for name in weights)
    eval_output = run_cli("lerobot-eval", f"--policy.path={pretrained}", "--env.type=bcrl_lift",
                          "--env.obs_type=pixels_agent_pos", "--env.episode_length=6", "--eval.n_episodes=1",
                          "--eval.batch_size=1", "--eval.use_async_envs=false", "--policy.device=cpu",
                          f"--output_dir={tmp_path / 'eval'}")
    assert "pc_success" in eval_output
