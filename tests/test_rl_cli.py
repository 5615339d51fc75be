"""bcrl-finetune through its console script: a killed run resumes with the same theta_t and step count, and a
BC+RL smoke run on Lift from a lerobot-train checkpoint ends in a checkpoint lerobot-eval evaluates."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from safetensors.torch import load_file
from policy_fixtures import lowdim_dataset_root  # noqa: F401

from lerobot_bcrl.rl.schedule import ScheduleConfig, theta_at

BIN = Path(sys.executable).parent


def run_cli(name: str, *args: str, timeout: int = 150) -> str:
    result = subprocess.run([str(BIN / name), *args], capture_output=True, text=True, timeout=timeout,
                            env=os.environ.copy())
    assert result.returncode == 0, (result.stdout + result.stderr)[-4000:]
    return result.stdout + result.stderr


def finetune_args(dataset_root: Path, output_dir: Path, total_env_steps: int, *extra: str) -> list[str]:
    return [
        f"--dataset.repo_id=local/{dataset_root.name}", f"--dataset.root={dataset_root}",
        "--env.type=bcrl_lift", "--env.episode_length=40", f"--total_env_steps={total_env_steps}",
        "--rollout.n_workers=0", "--rollout.envs_per_worker=2", "--rollout.steps_per_env=64",
        "--ppo.minibatch_size=64", "--bc_batch_size=32", "--save_freq=128", "--eval_freq=0",
        "--final_eval_episodes=1", "--tensorboard=false", f"--output_dir={output_dir}", *extra,
    ]


@pytest.mark.slow
def test_killed_run_resumes_with_same_theta_and_step_count(lowdim_dataset_root, tmp_path):
    extra = ["--policy.type=bcrl", "--policy.push_to_hub=false", "--ppo.learning_rate=1e-4", "--ppo.reset_log_std=-1.0",
             "--schedule.type=three_phase", "--schedule.alpha=4",
             "--schedule.beta=10", "--schedule.phi=40"]  # fmt: skip
    # A budget it cannot reach before the kill, whatever the machine's speed; the resumed run is given a target
    # two iterations past wherever the kill landed.
    args = finetune_args(lowdim_dataset_root, tmp_path / "run", 10**7, *extra)
    process = subprocess.Popen([str(BIN / "bcrl-finetune"), *args], stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL, env=os.environ.copy())
    last = tmp_path / "run" / "checkpoints" / "last"
    deadline = time.time() + 600  # generous: a slow machine only makes the first checkpoint later
    while not last.exists() and process.poll() is None and time.time() < deadline:
        time.sleep(0.1)
    assert process.poll() is None, "the run ended before its first checkpoint"
    process.send_signal(signal.SIGKILL)  # kill it right after its first checkpoint
    process.wait()
    killed_at = json.loads((last / "training_state" / "training_step.json").read_text())
    assert killed_at["env_steps"] % 128 == 0 and killed_at["env_steps"] >= 128

    killed_log_std = load_file(last / "pretrained_model" / "model.safetensors")["log_std"]
    assert killed_log_std.shape == (6,) and not np.allclose(killed_log_std.numpy(), -1.0)  # learned from its reset value

    target = killed_at["env_steps"] + 256
    output = run_cli("bcrl-finetune", *finetune_args(lowdim_dataset_root, tmp_path / "run", target, *extra), "--resume=true")
    final = json.loads((last / "training_state" / "training_step.json").read_text())
    # 128 env steps per iteration, 4 epochs x 2 minibatches: 8 optimisation steps each, whatever the kill.
    n_iterations = target // 128
    assert final["env_steps"] == target and final["optim_step"] == 8 * n_iterations
    assert final["ppo_iteration"] == n_iterations
    cfg = ScheduleConfig(type="three_phase", alpha=4, beta=10.0, phi=40)
    assert final["theta"] == pytest.approx(theta_at(cfg, 8 * n_iterations))
    rows = list(csv.DictReader((tmp_path / "run" / "logs.csv").open()))
    # no duplicate rows from the killed run (it may have logged an iteration past its last checkpoint)
    assert [int(r["env_steps"]) for r in rows] == list(range(128, target + 1, 128))
    first_resumed = rows[killed_at["env_steps"] // 128]
    assert int(first_resumed["optim_step"]) == killed_at["optim_step"] + 8  # the counters went on, not restarted
    assert f"{target} env steps" in output
    result = json.loads((tmp_path / "run" / "eval_final.json").read_text())
    assert result["eval_episodes"] == 1 and [e["seed"] for e in result["episodes"]] == [1_000_000]


@pytest.mark.slow
def test_bc_plus_rl_smoke_on_lift_through_the_real_commands(lowdim_dataset_root, tmp_path):
    run_cli("lerobot-train", "--policy.type=bcrl", f"--dataset.repo_id=local/{lowdim_dataset_root.name}",
            f"--dataset.root={lowdim_dataset_root}", "--policy.push_to_hub=false", "--steps=2", "--batch_size=8",
            f"--output_dir={tmp_path / 'bc'}", "--num_workers=0", "--policy.device=cpu", "--save_freq=2")
    bc_checkpoint = tmp_path / "bc" / "checkpoints" / "last" / "pretrained_model"
    output = run_cli("bcrl-finetune", f"--policy.path={bc_checkpoint}",
                     *finetune_args(lowdim_dataset_root, tmp_path / "bcrl", 256), "--eval_rerun=true",
                     "--policy.critic_hidden_dims=[32]")  # a fresh separate critic on the BC checkpoint
    assert "bcrl-finetune (BC+RL)" in output
    # the evaluation episode in rerun: what happened, the policy's predictions and values, and theta_t
    from lerobot_bcrl.rerun_log import read_entity_rows

    (rrd,) = (tmp_path / "bcrl" / "eval_rrd").glob("*.rrd")
    rows = read_entity_rows(rrd)
    assert rows["/state"] == 40 and rows["/policy/action"] == 40 and rows["/signals/value"] == 40
    assert rows["/signals/theta_t"] == 1 and rows["/signals/env_steps"] == 1
    result = json.loads((tmp_path / "bcrl" / "eval_final.json").read_text())
    assert result["method"] == "BC+RL" and result["env_steps"] == 256 and 0 < result["theta"] < 1
    assert result["policy_path"] == str(bc_checkpoint) and result["policy_env_steps"] == 0  # lerobot-train's BC
    rows = list(csv.DictReader((tmp_path / "bcrl" / "logs.csv").open()))
    assert float(rows[-1]["bc_loss"]) > 0 and rows[-1]["approx_kl"] != ""  # both terms were computed
    assert all(0 < float(row["bc_grad_share"]) <= 1 for row in rows)  # measured once per iteration
    for part in ("simulation_s", "policy_s", "learner_data_s", "bc_term_s", "update_s"):  # where the time went
        assert all(float(row[part]) > 0 for row in rows), part
    assert all(float(row["rendering_s"]) == 0 for row in rows)  # low-dim envs render no camera
    pretrained = tmp_path / "bcrl" / "checkpoints" / "last" / "pretrained_model"
    for name in ("config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json"):
        assert (pretrained / name).exists(), name
    assert (pretrained.parent / "training_state" / "optimizer_state.safetensors").exists()
    assert json.loads((pretrained / "config.json").read_text())["critic_hidden_dims"] == [32]
    eval_output = run_cli("lerobot-eval", f"--policy.path={pretrained}", "--env.type=bcrl_lift",
                          "--env.obs_type=agent_pos", "--env.episode_length=8", "--eval.n_episodes=1",
                          "--eval.batch_size=1", "--eval.use_async_envs=false", "--policy.device=cpu",
                          f"--output_dir={tmp_path / 'eval'}")
    assert "pc_success" in eval_output
    # evaluating the fine-tuned checkpoint alone: the result counts the env steps behind it
    run_cli("bcrl-finetune", f"--policy.path={pretrained}", *finetune_args(lowdim_dataset_root, tmp_path / "again", 0),
            "--seed=7")
    evaluated = json.loads((tmp_path / "again" / "eval_final.json").read_text())
    assert evaluated["env_steps"] == 0 and evaluated["policy_env_steps"] == 256
    assert evaluated["method"] == "BC+RL"  # a fine-tuned checkpoint, not "BC" because this run trained nothing
    assert result["seed"] == 1000 and evaluated["seed"] == 7  # the training seed, for bcrl-report's per-seed cells


@pytest.mark.slow
def test_best_validation_selection_evaluates_the_chosen_checkpoint_on_the_test_seeds(lowdim_dataset_root, tmp_path):
    from lerobot_bcrl.rl.checkpoint import checkpoint_name
    from lerobot_bcrl.rl.ppo import EVAL_SEED_OFFSET, VALIDATION_SEED_OFFSET

    run = tmp_path / "run"
    # the dense reward, so that evaluations differ in return and the choice is not a tie of zeros
    flags = ["--policy.type=bcrl", "--policy.push_to_hub=false", "--env.dense_reward=true", "--select=best_validation",
             "--eval_freq=128", "--eval_episodes=2", "--final_eval_episodes=2"]
    first = [a for a in finetune_args(lowdim_dataset_root, run, 256) if not a.startswith("--eval_freq")]
    run_cli("bcrl-finetune", *first, *flags)
    chosen_before = json.loads((run / "eval_final.json").read_text())["selected_env_steps"]
    # resumed with a larger budget: the choice so far goes on from the checkpoint, the start is not evaluated again
    args = [a for a in finetune_args(lowdim_dataset_root, run, 384) if not a.startswith("--eval_freq")]
    output = run_cli("bcrl-finetune", *args, *flags, "--resume=true")
    rows = [r for r in csv.DictReader((run / "logs.csv").open()) if r["eval_return"]]
    assert [int(r["env_steps"]) for r in rows] == [0, 128, 256, 384]  # the starting policy is a candidate
    assert chosen_before in (0, 128, 256)
    returns = [float(r["eval_return"]) for r in rows]
    assert len(set(returns)) > 1  # the policies differ on the validation seeds
    chosen = max(rows, key=lambda r: (float(r["eval_success"]), float(r["eval_return"])))  # max keeps the earliest
    result = json.loads((run / "eval_final.json").read_text())
    assert result["select"] == "best_validation" and result["env_steps"] == 384
    assert result["selected_env_steps"] == int(chosen["env_steps"])
    assert result["validation"]["return"] == pytest.approx(float(chosen["eval_return"]))
    assert result["validation"]["seed_offset"] == VALIDATION_SEED_OFFSET and result["validation"]["episodes"] == 2
    assert [e["seed"] for e in result["episodes"]] == [EVAL_SEED_OFFSET, EVAL_SEED_OFFSET + 1]  # test seeds, not validation
    best = run / "checkpoints" / "best"
    assert best.resolve().name == checkpoint_name(result["selected_env_steps"])
    assert (run / "checkpoints" / "last").resolve().name == checkpoint_name(384)  # resume goes on from the last
    saved = json.loads((run / "checkpoints" / "last" / "training_state" / "training_step.json").read_text())
    assert saved["best"]["env_steps"] == result["selected_env_steps"]  # a resumed run keeps the choice
    assert f"the policy at {result['selected_env_steps']} env steps" in output and "checkpoints/best/" in output

    # the final evaluation was the chosen checkpoint's: evaluating it alone gives the same episodes
    run_cli("bcrl-finetune", f"--policy.path={best / 'pretrained_model'}", *finetune_args(lowdim_dataset_root, tmp_path / "again", 0),
            "--env.dense_reward=true", "--final_eval_episodes=2")
    again = json.loads((tmp_path / "again" / "eval_final.json").read_text())
    assert [e["episode_return"] for e in again["episodes"]] == pytest.approx([e["episode_return"] for e in result["episodes"]])


@pytest.mark.slow
def test_reselection_evaluates_every_tied_checkpoint_again_and_keeps_the_best_over_all_validation_episodes(
        lowdim_dataset_root, tmp_path):
    from lerobot_bcrl.rl.checkpoint import checkpoint_name
    from lerobot_bcrl.rl.ppo import EVAL_SEED_OFFSET, VALIDATION_SEED_OFFSET

    run = tmp_path / "run"
    # from scratch no policy lifts in 40 steps: every validation ties on success 0 and the dense return decides;
    # checkpoints only at the end, so the tied ones on disk were saved for the reselection
    args = [a for a in finetune_args(lowdim_dataset_root, run, 256) if not a.startswith(("--eval_freq", "--save_freq"))]
    output = run_cli("bcrl-finetune", *args, "--policy.type=bcrl", "--policy.push_to_hub=false", "--env.dense_reward=true",
                     "--select=best_validation", "--eval_freq=128", "--eval_episodes=2", "--reselect_episodes=3",
                     "--save_freq=100000", "--final_eval_episodes=2")
    rows = [r for r in csv.DictReader((run / "logs.csv").open()) if r["eval_return"]]
    assert [int(r["env_steps"]) for r in rows] == [0, 128, 256] and {float(r["eval_success"]) for r in rows} == {0.0}
    result = json.loads((run / "eval_final.json").read_text())
    chosen = result["validation"]
    candidates = chosen["candidates"]
    assert [c["env_steps"] for c in candidates] == [0, 128, 256]  # every tied policy was saved and evaluated again
    assert all((run / "checkpoints" / checkpoint_name(c["env_steps"])).is_dir() for c in candidates)
    for candidate, row in zip(candidates, rows):  # pooled over the first 2 and the 3 further validation episodes
        again_mean = (5 * candidate["return"] - 2 * float(row["eval_return"])) / 3
        assert candidate["episodes"] == 5 and again_mean > 0  # the dense reward is positive at every step
    assert chosen["first_choice"]["env_steps"] == int(max(rows, key=lambda r: float(r["eval_return"]))["env_steps"])
    best = max(candidates, key=lambda c: (c["success"], c["return"]))
    assert result["selected_env_steps"] == best["env_steps"] and chosen["seed_offset"] == VALIDATION_SEED_OFFSET
    assert (run / "checkpoints" / "best").resolve().name == checkpoint_name(best["env_steps"])
    assert [e["seed"] for e in result["episodes"]] == [EVAL_SEED_OFFSET, EVAL_SEED_OFFSET + 1]
    assert "among the 3 that tied on the first 2" in output


@pytest.mark.slow
def test_dense_training_reward_leaves_validation_and_test_on_the_envs_reward(lowdim_dataset_root, tmp_path):
    run = tmp_path / "run"
    run_cli("bcrl-finetune", *finetune_args(lowdim_dataset_root, run, 128, "--policy.type=bcrl", "--policy.push_to_hub=false",
                                            "--rollout.dense_reward=true", "--eval_freq=128", "--eval_episodes=1"))
    rows = list(csv.DictReader((run / "logs.csv").open()))
    trained = [r for r in rows if r["train_return"]]
    validated = [r for r in rows if r["eval_return"]]
    assert trained and validated
    # robosuite's reaching term is > 0 at every step: a shaped episode's return is never 0 nor a multiple of 2.25
    for row in trained:
        assert float(row["train_return"]) > 0 and float(row["train_return"]) / 2.25 % 1 > 1e-6
    # the sparse reward: 2.25 for each lifted step, 0 otherwise
    for row in validated:
        assert float(row["eval_return"]) / 2.25 % 1 == pytest.approx(0, abs=1e-6)
    for episode in json.loads((run / "eval_final.json").read_text())["episodes"]:
        assert episode["episode_return"] == pytest.approx(2.25 * episode["lifted_steps"], abs=1e-6)


def test_dense_training_reward_needs_an_env_that_has_one(tmp_path):
    from lerobot.envs.configs import PushtEnv

    from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig
    from lerobot_bcrl.rl.configuration import FinetuneConfig, RolloutConfig
    from lerobot_bcrl.rl.ppo import finetune

    cfg = FinetuneConfig(policy=BCRLConfig(), env=PushtEnv(), rollout=RolloutConfig(dense_reward=True),
                         output_dir=tmp_path / "run")
    with pytest.raises(ValueError, match="--rollout.dense_reward"):
        finetune(cfg)
    assert not (tmp_path / "run").exists()


def test_best_validation_selection_needs_periodic_evaluations(tmp_path):
    from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig
    from lerobot_bcrl.rl.configuration import FinetuneConfig
    from lerobot_bcrl.rl.ppo import finetune

    cfg = FinetuneConfig(policy=BCRLConfig(), select="best_validation", eval_freq=0, total_env_steps=128,
                         output_dir=tmp_path / "run")
    with pytest.raises(ValueError, match="--eval_freq > 0"):
        finetune(cfg)
    with pytest.raises(ValueError, match="choose one of"):
        finetune(FinetuneConfig(policy=BCRLConfig(), select="best", output_dir=tmp_path / "run"))
    assert not (tmp_path / "run").exists()  # refused before anything was written


def test_learner_threads_hold_for_the_update_only(lowdim_dataset_root, tmp_path, monkeypatch):
    """--learner_threads=2: the update runs on two torch threads, the collect (an in-process worker here) on one."""
    import torch

    from lerobot_bcrl.envs.configuration_lift import LiftEnvConfig
    from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig
    from lerobot_bcrl.rl import ppo
    from lerobot_bcrl.rl.configuration import DemoDatasetConfig, FinetuneConfig, RolloutConfig

    threads_seen = {"collect": [], "update": []}
    real_update, real_start = ppo.ppo_update, ppo.start_workers

    def update(*args, **kwargs):
        threads_seen["update"].append(torch.get_num_threads())
        return real_update(*args, **kwargs)

    def start_workers(*args, **kwargs):
        workers = real_start(*args, **kwargs)
        collect = workers.collect

        def counted_collect(*a, **k):
            threads_seen["collect"].append(torch.get_num_threads())
            return collect(*a, **k)

        monkeypatch.setattr(workers, "collect", counted_collect)
        return workers

    monkeypatch.setattr(ppo, "ppo_update", update)
    monkeypatch.setattr(ppo, "start_workers", start_workers)
    cfg = FinetuneConfig(
        policy=BCRLConfig(push_to_hub=False), env=LiftEnvConfig(obs_type="agent_pos", episode_length=40),
        dataset=DemoDatasetConfig(repo_id=f"local/{lowdim_dataset_root.name}", root=str(lowdim_dataset_root)),
        rollout=RolloutConfig(n_workers=0, envs_per_worker=2, steps_per_env=32), total_env_steps=128,
        bc_batch_size=32, save_freq=128, eval_freq=0, final_eval_episodes=1, tensorboard=False,
        learner_threads=2, output_dir=tmp_path / "run")
    cfg.ppo.minibatch_size = 32
    ppo.finetune(cfg)
    assert threads_seen == {"collect": [1, 1], "update": [2, 2]}

    with pytest.raises(ValueError, match="--learner_threads=0"):
        ppo.finetune(FinetuneConfig(policy=BCRLConfig(), learner_threads=0, output_dir=tmp_path / "refused"))
    assert not (tmp_path / "refused").exists()
