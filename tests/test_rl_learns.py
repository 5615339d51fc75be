"""PPO (the same `ppo_update` and rollout workers bcrl-finetune uses) learns a tiny continuous task quickly,
and the workers are reproducible: same seed and weights, same trajectories."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from torch import nn
from torch.distributions import Normal

from lerobot_bcrl.rl.ppo import PPOConfig, ppo_loss_terms, ppo_update
from lerobot_bcrl.rl.rollout import InlineWorkers
from lerobot_bcrl.rl.schedule import ScheduleConfig, ScheduleState


class ReachOrigin(gym.Env):
    """A point on a line starts in [-1, 1] and is pushed by a in [-1, 1]: reward -|x|, 20 steps."""

    observation_space = gym.spaces.Box(-2.0, 2.0, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.t = float(self.np_random.uniform(-1, 1)), 0
        return np.array([self.x], np.float32), {}

    def step(self, action):
        self.x = float(np.clip(self.x + 0.2 * np.clip(action[0], -1, 1), -2, 2))
        self.t += 1
        return np.array([self.x], np.float32), -abs(self.x), False, self.t >= 20, {"is_success": abs(self.x) < 0.1}


class MLPAgent:
    noise_dims = 1

    def __init__(self):
        torch.manual_seed(0)
        self.module = nn.ModuleDict({"actor": nn.Sequential(nn.Linear(1, 32), nn.Tanh(), nn.Linear(32, 1)),
                                     "critic": nn.Sequential(nn.Linear(1, 32), nn.Tanh(), nn.Linear(32, 1))})
        self.module.log_std = nn.Parameter(torch.zeros(1))

    def state_dict(self):
        return self.module.state_dict()

    def load_state_dict(self, state):
        self.module.load_state_dict(state)

    def observation_batch(self, raw_obs):
        return {"obs": torch.as_tensor(raw_obs["obs"], dtype=torch.float32)}

    def _dist(self, obs):
        return Normal(self.module["actor"](obs["obs"]), self.module.log_std.exp())

    def sample(self, obs, noise=None):
        dist = self._dist(obs)
        actions = dist.sample() if noise is None else dist.mean + dist.stddev * noise
        return actions, dist.log_prob(actions).sum(-1), self.value(obs)

    def to_env_action(self, actions):
        return actions

    def mean_action(self, obs):
        return self._dist(obs).mean

    def value(self, obs):
        return self.module["critic"](obs["obs"]).squeeze(-1)

    def evaluate(self, obs, actions):
        dist = self._dist(obs)
        return dist.log_prob(actions).sum(-1), {"action": dist.entropy().sum(-1)}, self.value(obs)

    def term_norm_parameters(self):
        return list(self.module.parameters())


def make_workers(seed: int) -> InlineWorkers:
    return InlineWorkers([{"make_env": ReachOrigin, "make_agent": MLPAgent, "n_envs": 4, "seed": seed}])


def test_ppo_learns_reach_origin_in_a_few_thousand_steps():
    learner = MLPAgent()
    workers = make_workers(seed=1)
    evaluation_seeds = list(range(100, 120))
    before = np.mean([e.episode_return for e in workers.evaluate(learner.module.state_dict(), evaluation_seeds)])
    cfg = PPOConfig(learning_rate=3e-3, minibatch_size=64, update_epochs=4, max_grad_norm=0.5, gamma=0.95)
    optimizer = torch.optim.Adam(learner.module.parameters(), lr=cfg.learning_rate)
    schedule_cfg, schedule_state = ScheduleConfig(type="constant", constant_theta=0.0), ScheduleState()
    for _ in range(20):  # 20 x 4 envs x 64 steps = 5120 env steps
        trajectories = workers.collect(learner.module.state_dict(), 64)
        ppo_update(learner, optimizer, trajectories, trajectories.rewards, cfg, schedule_cfg, schedule_state)
    after = np.mean([e.episode_return for e in workers.evaluate(learner.module.state_dict(), evaluation_seeds)])
    # Doing nothing from x ~ U(-1, 1) costs ~ -10 per episode; walking to the origin costs ~ -3.
    assert after > before + 3.0, (before, after)
    assert after > -5.0, after
    assert schedule_state.optim_step == 20 * 4 * (256 // 64) and schedule_state.ppo_iteration == 20


def test_target_kl_stops_an_iteration_before_the_policy_moves_far():
    """With `target_kl`, an iteration whose minibatch approx-KL passes the target takes no more steps: fewer steps,
    and the updated policy ends closer to the one that collected the batch than without the stop."""
    trajectories = make_workers(seed=3).collect(MLPAgent().module.state_dict(), 64)
    schedule_cfg = ScheduleConfig(type="constant", constant_theta=0.0)

    def update(target_kl):
        learner = MLPAgent()
        cfg = PPOConfig(learning_rate=3e-3, minibatch_size=64, update_epochs=4, gamma=0.95, target_kl=target_kl)
        optimizer = torch.optim.Adam(learner.module.parameters(), lr=cfg.learning_rate)
        schedule_state = ScheduleState()
        metrics = ppo_update(learner, optimizer, trajectories, trajectories.rewards, cfg, schedule_cfg, schedule_state)
        obs = {"obs": torch.as_tensor(trajectories.observations["obs"].reshape(-1, 1), dtype=torch.float32)}
        actions = torch.as_tensor(trajectories.actions.reshape(-1, 1))
        with torch.no_grad():
            new_log_prob, _, value = learner.evaluate(obs, actions)
            old_log_prob = torch.as_tensor(trajectories.log_probs.reshape(-1))
            kl = float(ppo_loss_terms(new_log_prob, old_log_prob, value, value, value, cfg.clip_eps)["approx_kl"])
        assert metrics["optim_steps_taken"] == schedule_state.optim_step
        return metrics, kl

    free, free_kl = update(None)
    stopped, stopped_kl = update(0.005)
    assert free["optim_steps_taken"] == 4 * (256 // 64) and free["kl_stopped"] == 0.0
    assert free_kl > 0.01, free_kl  # the learning rate moves the policy past the target without the stop
    assert 1 <= stopped["optim_steps_taken"] < free["optim_steps_taken"] and stopped["kl_stopped"] == 1.0
    assert stopped_kl < 0.5 * free_kl, (stopped_kl, free_kl)
    with pytest.raises(ValueError, match="target_kl must be positive"):
        PPOConfig(target_kl=0.0)


def test_workers_are_reproducible():
    state = MLPAgent().module.state_dict()
    first, second = make_workers(seed=7).collect(state, 30), make_workers(seed=7).collect(state, 30)
    other = make_workers(seed=8).collect(state, 30)
    np.testing.assert_array_equal(first.actions, second.actions)
    np.testing.assert_array_equal(first.observations["obs"], second.observations["obs"])
    np.testing.assert_array_equal(first.truncation_values, second.truncation_values)
    assert not np.array_equal(first.observations["obs"], other.observations["obs"])
    # 30 steps of 20-step episodes: every env finished exactly one episode, bootstrapped at its time limit.
    assert len(first.episodes) == 4 and first.dones.sum() == 4
    assert np.all((first.truncation_values != 0) == (first.dones == 1))


def test_a_dead_worker_is_named_not_a_bare_eof_error():
    """A worker killed mid-run (e.g. by the OOM killer) that may not be replaced (`max_failures=1`) gives an error
    naming it, its exit code and --resume."""
    from lerobot_bcrl.rl.rollout import ProcessWorkers

    state = MLPAgent().module.state_dict()
    kwargs = [{"make_env": ReachOrigin, "make_agent": MLPAgent, "n_envs": 1, "seed": i} for i in range(2)]
    processes = ProcessWorkers(kwargs, max_failures=1)
    try:
        processes.collect(state, 5)
        os.kill(processes.processes[1].pid, signal.SIGKILL)
        processes.processes[1].join(timeout=10)
        with pytest.raises(RuntimeError, match=r"rollout worker 1 \(pid \d+\) died with exit code -9.*--resume=true"):
            processes.collect(state, 5)
    finally:
        processes.close()


class SlowReachOrigin(ReachOrigin):
    """ReachOrigin at 100 steps/s: a rollout long enough to be killed in the middle of."""

    def step(self, action):
        time.sleep(0.01)
        return super().step(action)


def _alive(pid: int) -> bool:
    """Running or sleeping; a zombie (dead, not yet reaped by whoever inherited it) counts as gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the kernel's parent-death signal is Linux's")
def test_workers_die_with_a_killed_learner_instead_of_finishing_their_rollout():
    """SIGKILL the learner while its workers are 100 s into a rollout: they are gone within seconds, not
    left as orphans holding the cores until the rollout ends."""
    driver = (
        "from test_rl_learns import MLPAgent, SlowReachOrigin\n"
        "from lerobot_bcrl.rl.rollout import ProcessWorkers\n"
        "kwargs = [{'make_env': SlowReachOrigin, 'make_agent': MLPAgent, 'n_envs': 1, 'seed': i} for i in range(2)]\n"
        "workers = ProcessWorkers(kwargs)\n"
        "print(*[p.pid for p in workers.processes], flush=True)\n"
        "workers.collect(MLPAgent().module.state_dict(), 10_000)\n"
    )
    python_path = [str(Path(__file__).parent), *filter(None, [os.environ.get("PYTHONPATH")])]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(python_path)}
    learner = subprocess.Popen([sys.executable, "-c", driver], stdout=subprocess.PIPE, text=True, env=env)
    worker_pids = []
    try:
        worker_pids = [int(pid) for pid in learner.stdout.readline().split()]
        assert len(worker_pids) == 2 and all(_alive(pid) for pid in worker_pids), worker_pids
        time.sleep(1.0)  # the collect command has reached the workers
        assert all(_alive(pid) for pid in worker_pids)
        learner.kill()
        learner.wait(timeout=10)
        deadline = time.monotonic() + 30
        while any(_alive(pid) for pid in worker_pids) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(_alive(pid) for pid in worker_pids), f"orphaned rollout workers still running: {worker_pids}"
    finally:
        learner.kill()
        for pid in worker_pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def test_evaluation_is_reproducible_and_leaves_the_training_rollouts_alone():
    """An evaluation plays the same episodes from the same seeds whatever the workers' own seed, and collecting
    after it gives the trajectories collecting would have given without it."""
    state = MLPAgent().module.state_dict()
    seeds = [20, 21, 22]
    workers = make_workers(seed=5)
    evaluated = [e.episode_return for e in workers.evaluate(state, seeds)]
    after_eval = workers.collect(state, 30)
    assert evaluated == [e.episode_return for e in make_workers(seed=9).evaluate(state, seeds)]
    assert [e.seed for e in workers.evaluate(state, seeds)] == seeds
    np.testing.assert_array_equal(after_eval.actions, make_workers(seed=5).collect(state, 30).actions)
