"""Rollout collection behind one small interface: workers take policy weights and return trajectories.

`RolloutWorker` owns a few env copies and a copy of the agent; `InlineWorkers` runs them in this process,
`ProcessWorkers` one per subprocess. A Ray pool would wrap the same `RolloutWorker` class (`ray.remote`).
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing as mp
import os
import signal
import sys
from dataclasses import dataclass, field
from typing import Callable, Protocol

import gymnasium as gym
import numpy as np
import torch

from lerobot_bcrl import rerun_log
from lerobot_bcrl.rl.agent import Agent, flatten_observation


@dataclass
class EpisodeStats:
    episode_return: float
    length: int
    success: bool  # the cube was lifted at some step (info["is_success"] ever true)
    steps_to_lift: int | None  # first step (1-based) with info["is_success"], None if never
    seed: int | None = None
    lifted_steps: int = 0  # steps with info["is_success"]; fewer than length - steps_to_lift + 1: the cube was lost again

    def record_step(self, reward: float, info: dict) -> None:
        self.episode_return += float(reward)
        self.length += 1
        lifted = bool(info.get("is_success", False))
        self.lifted_steps += int(lifted)
        if lifted and not self.success:
            self.success, self.steps_to_lift = True, self.length


@dataclass
class Trajectories:
    """T steps of N envs, time-major; the learner bootstraps truncated episodes with `truncation_values`."""

    observations: dict[str, np.ndarray]  # (T, N, ...) raw env observations, flattened keys
    actions: np.ndarray  # (T, N, A) as the agent samples them (before `to_env_action`)
    log_probs: np.ndarray  # (T, N)
    values: np.ndarray  # (T, N)
    rewards: np.ndarray  # (T, N) env rewards
    truncation_values: np.ndarray  # (T, N) V(s_{t+1}) where the episode hit the time limit at t, else 0
    dones: np.ndarray  # (T, N) 1.0 where the episode ended with this step
    last_values: np.ndarray  # (N,) V of the observation after the last step
    episodes: list[EpisodeStats] = field(default_factory=list)  # episodes that ended in this rollout

    @staticmethod
    def concatenate(parts: list[Trajectories]) -> Trajectories:
        """Join trajectories of different workers along the env axis."""
        cat = lambda arrays: np.concatenate(arrays, axis=1)  # noqa: E731
        return Trajectories(
            observations={k: cat([p.observations[k] for p in parts]) for k in parts[0].observations},
            actions=cat([p.actions for p in parts]),
            log_probs=cat([p.log_probs for p in parts]),
            values=cat([p.values for p in parts]),
            rewards=cat([p.rewards for p in parts]),
            truncation_values=cat([p.truncation_values for p in parts]),
            dones=cat([p.dones for p in parts]),
            last_values=np.concatenate([p.last_values for p in parts]),
            episodes=[e for p in parts for e in p.episodes],
        )


def stack_observations(observations: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {key: np.stack([o[key] for o in observations]) for key in observations[0]}


class RolloutWorker:
    """`n_envs` env copies and one agent. Envs keep running across `collect` calls (episodes span rollouts).

    Episode seeds come from a generator seeded with `seed`, actions from torch's RNG seeded with `seed`:
    the same weights give the same trajectories.
    """

    def __init__(self, make_env: Callable[[], gym.Env], make_agent: Callable[[], Agent], n_envs: int,
                 seed: int, make_eval_env: Callable[[], gym.Env] | None = None):
        self.agent = make_agent()
        # Each worker owns its torch RNG stream (swapped in around collect/evaluate), so several workers in
        # one process draw the same actions as the same workers in separate processes.
        outer_rng = torch.get_rng_state()
        torch.manual_seed(seed)  # after the agent is built: its initialisation may seed torch itself
        self._torch_rng = torch.get_rng_state()
        torch.set_rng_state(outer_rng)
        self.envs = [make_env() for _ in range(n_envs)]
        self.make_eval_env = make_eval_env or make_env  # e.g. one that logs its episodes to rerun
        self.eval_env: gym.Env | None = None
        self.seed_rng = np.random.default_rng(seed)
        self.observations, self.running = [], []
        for env in self.envs:
            obs, stats = self._reset(env)
            self.observations.append(obs)
            self.running.append(stats)

    def _reset(self, env: gym.Env) -> tuple[dict[str, np.ndarray], EpisodeStats]:
        episode_seed = int(self.seed_rng.integers(2**31))
        obs, _ = env.reset(seed=episode_seed)
        return flatten_observation(obs), EpisodeStats(0.0, 0, False, None, seed=episode_seed)

    def _load(self, state_dict: dict[str, torch.Tensor] | None) -> None:
        if state_dict is not None:
            self.agent.load_state_dict(state_dict)

    @contextlib.contextmanager
    def _own_rng(self):
        outer_rng = torch.get_rng_state()
        torch.set_rng_state(self._torch_rng)
        try:
            yield
        finally:
            self._torch_rng = torch.get_rng_state()
            torch.set_rng_state(outer_rng)

    def collect(self, state_dict: dict[str, torch.Tensor] | None, steps_per_env: int) -> Trajectories:
        with self._own_rng(), torch.no_grad():
            return self._collect(state_dict, steps_per_env)

    def _collect(self, state_dict: dict[str, torch.Tensor] | None, steps_per_env: int) -> Trajectories:
        self._load(state_dict)
        self.agent.module.eval()
        n_envs = len(self.envs)
        obs_steps, action_steps, log_prob_steps, value_steps = [], [], [], []
        rewards = np.zeros((steps_per_env, n_envs), np.float32)
        truncation_values = np.zeros((steps_per_env, n_envs), np.float32)
        dones = np.zeros((steps_per_env, n_envs), np.float32)
        finished: list[EpisodeStats] = []
        for t in range(steps_per_env):
            raw_obs = stack_observations(self.observations)
            actions, log_probs, values = self.agent.sample(self.agent.observation_batch(raw_obs))
            obs_steps.append(raw_obs)
            action_steps.append(actions.numpy())
            log_prob_steps.append(log_probs.numpy())
            value_steps.append(values.numpy())
            env_actions = self.agent.to_env_action(actions).numpy()
            for i, env in enumerate(self.envs):
                obs, reward, terminated, truncated, info = env.step(env_actions[i])
                self.running[i].record_step(reward, info)
                rewards[t, i] = reward
                obs = flatten_observation(obs)
                if terminated or truncated:
                    if truncated and not terminated:  # time limit: bootstrap from the state we stopped in
                        last_obs = self.agent.observation_batch(stack_observations([obs]))
                        truncation_values[t, i] = float(self.agent.value(last_obs)[0])
                    dones[t, i] = 1.0
                    finished.append(self.running[i])
                    obs, self.running[i] = self._reset(env)
                self.observations[i] = obs
        last_values = self.agent.value(self.agent.observation_batch(stack_observations(self.observations)))
        return Trajectories(
            observations={k: np.stack([o[k] for o in obs_steps]) for k in obs_steps[0]},
            actions=np.stack(action_steps),
            log_probs=np.stack(log_prob_steps),
            values=np.stack(value_steps),
            rewards=rewards,
            truncation_values=truncation_values,
            dones=dones,
            last_values=last_values.numpy(),
            episodes=finished,
        )

    @torch.no_grad()
    def evaluate(self, state_dict: dict[str, torch.Tensor] | None, seeds: list[int],
                 annotations: dict[str, float] | None = None) -> list[EpisodeStats]:
        """Deterministic episodes (mean, argmax) from the given seeds on a separate env. `annotations` (e.g.
        theta_t, env steps) go beside them into rerun when the eval env logs there."""
        self._load(state_dict)
        self.agent.module.eval()
        if self.eval_env is None:
            self.eval_env = self.make_eval_env()
        results = []
        for episode_seed in seeds:
            results.append(self._evaluate_episode(int(episode_seed), annotations))
        return results

    def _evaluate_episode(self, episode_seed: int, annotations: dict[str, float] | None) -> EpisodeStats:
        obs, _ = self.eval_env.reset(seed=episode_seed)
        rerun_log.annotate_rollouts(annotations or {})
        stats = EpisodeStats(0.0, 0, False, None, seed=episode_seed)
        done = False
        while not done:
            batch = self.agent.observation_batch(stack_observations([flatten_observation(obs)]))
            action = self.agent.mean_action(batch)[0].numpy()
            obs, reward, terminated, truncated, info = self.eval_env.step(action)
            stats.record_step(reward, info)
            done = terminated or truncated
        return stats

    def close(self) -> None:
        for env in [*self.envs, self.eval_env]:
            if env is not None:
                env.close()


class RolloutWorkers(Protocol):
    """The interface the algorithm sees. Swap the implementation (process pool, Ray) without touching PPO.
    `state_dict` is the agent's (`Agent.state_dict()`: weights and any observation statistics)."""

    def collect(self, state_dict: dict[str, torch.Tensor], steps_per_env: int) -> Trajectories: ...
    def evaluate(self, state_dict: dict[str, torch.Tensor], seeds: list[int],
                 annotations: dict[str, float] | None = None) -> list[EpisodeStats]: ...
    def close(self) -> None: ...


def split_evenly(items: list, n_parts: int) -> list[list]:
    return [items[i::n_parts] for i in range(n_parts)]


class InlineWorkers:
    """The workers in this process, one after the other (tests, debugging, a single core)."""

    def __init__(self, worker_kwargs: list[dict]):
        self.workers = [RolloutWorker(**kwargs) for kwargs in worker_kwargs]

    def collect(self, state_dict, steps_per_env):
        return Trajectories.concatenate([w.collect(state_dict, steps_per_env) for w in self.workers])

    def evaluate(self, state_dict, seeds, annotations=None):
        parts = split_evenly(list(seeds), len(self.workers))
        return [e for w, part in zip(self.workers, parts) for e in w.evaluate(state_dict, part, annotations)]

    def close(self):
        for w in self.workers:
            w.close()


def _exit_with_the_learner() -> None:
    """Linux: have the kernel send this worker SIGTERM when the learner dies, however it dies (`kill`, the OOM
    killer), so that no orphan finishes a rollout nobody will read. Elsewhere the worker exits at its next
    command (the closed pipe). The kernel watches the thread that started the worker: start `ProcessWorkers`
    from one that lives as long as they do (bcrl-finetune: the main thread)."""
    if not sys.platform.startswith("linux"):
        return
    pr_set_pdeathsig = 1
    ctypes.CDLL(None).prctl(pr_set_pdeathsig, signal.SIGTERM)
    learner = mp.parent_process()
    if learner is not None and os.getppid() != learner.pid:  # the learner died before the prctl
        os._exit(1)


def _worker_main(connection, worker_kwargs: dict) -> None:
    _exit_with_the_learner()
    torch.set_num_threads(1)
    worker = RolloutWorker(**worker_kwargs)
    connection.send("ready")
    while True:
        try:
            command, args = connection.recv()
        except (EOFError, KeyboardInterrupt):  # the learner died: do not linger as an orphan
            command = "close"
        if command == "close":
            worker.close()
            connection.close()
            return
        connection.send(getattr(worker, command)(*args))


class ProcessWorkers:
    """One `RolloutWorker` per subprocess (spawned: safe with MuJoCo's EGL and torch threads)."""

    def __init__(self, worker_kwargs: list[dict]):
        context = mp.get_context("spawn")
        self.connections, self.processes = [], []
        for kwargs in worker_kwargs:
            parent, child = context.Pipe()
            process = context.Process(target=_worker_main, args=(child, kwargs), daemon=True)
            process.start()
            self.connections.append(parent)
            self.processes.append(process)
        for index in range(len(self.connections)):
            self._receive(index)  # "ready"

    def _receive(self, index: int):
        try:
            return self.connections[index].recv()
        except (EOFError, ConnectionResetError):
            self._raise_worker_died(index)

    def _raise_worker_died(self, index: int):
        """An error that says which worker died and how, instead of a bare EOFError / BrokenPipeError."""
        process = self.processes[index]
        process.join(timeout=5)
        code = process.exitcode
        how = " (SIGKILL: out of memory?)" if code == -9 else ""
        raise RuntimeError(
            f"rollout worker {index} (pid {process.pid}) died with exit code {code}{how}; its traceback, if it "
            "raised one, is printed above. Continue the run from its last checkpoint with --resume=true."
        ) from None

    def _call_all(self, command: str, per_worker_args: list[tuple]) -> list:
        for index, args in enumerate(per_worker_args):
            try:
                self.connections[index].send((command, args))
            except (BrokenPipeError, ConnectionResetError):
                self._raise_worker_died(index)
        return [self._receive(index) for index in range(len(self.connections))]

    def collect(self, state_dict, steps_per_env):
        state_dict = {k: v.detach().cpu() for k, v in state_dict.items()}
        parts = self._call_all("collect", [(state_dict, steps_per_env)] * len(self.connections))
        return Trajectories.concatenate(parts)

    def evaluate(self, state_dict, seeds, annotations=None):
        state_dict = {k: v.detach().cpu() for k, v in state_dict.items()}
        parts = self._call_all(
            "evaluate",
            [(state_dict, part, annotations) for part in split_evenly(list(seeds), len(self.connections))],
        )
        return [e for part in parts for e in part]

    def close(self):
        for connection in self.connections:
            try:
                connection.send(("close", ()))
            except (BrokenPipeError, OSError):
                pass
        for process in self.processes:
            process.join(timeout=10)
            if process.is_alive():
                process.terminate()


def make_workers(n_workers: int, worker_kwargs: list[dict]) -> RolloutWorkers:
    """`n_workers = 0`: inline; otherwise one subprocess per entry of `worker_kwargs`."""
    return InlineWorkers(worker_kwargs) if n_workers == 0 else ProcessWorkers(worker_kwargs)


def make_gym_env(gym_id: str, gym_kwargs: dict) -> gym.Env:
    """A picklable env factory (use with functools.partial)."""
    import lerobot_bcrl.envs  # noqa: F401  (registers gym_bcrl_lift)

    return gym.make(gym_id, disable_env_checker=True, **gym_kwargs)
