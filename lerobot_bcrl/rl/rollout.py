"""Rollout collection behind one small interface: workers take policy weights and return trajectories.

`RolloutWorker` owns a few env copies and a copy of the agent; `InlineWorkers` runs them in this process,
`ProcessWorkers` one per subprocess, `RayWorkers` one per Ray actor; the last two replace a worker that dies or hangs.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import multiprocessing as mp
import multiprocessing.connection as mp_connection
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

import gymnasium as gym
import numpy as np
import torch

from lerobot_bcrl import rerun_log
from lerobot_bcrl.rl.agent import Agent, flatten_observation
from lerobot_bcrl.rl.colored_noise import ColoredNoiseStream

logger = logging.getLogger(__name__)
WORKER_TIMEOUT_S = 900.0  # a worker that has not answered a collect or evaluation in this long is killed and replaced
MAX_WORKER_FAILURES = 3  # a worker failing this many calls in a row stops the run
# Starting a worker (imports, envs, agent; on Ray, waiting for a free CPU) may take minutes on a loaded machine: a
# start is given at least this long, whatever a collect's timeout.
START_TIMEOUT_S = 300.0


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
    # Seconds this rollout spent per part (each worker's wall time, summed over workers): "simulation" (env steps and
    # resets less rendering), "rendering" (the camera observations), "policy" (the rest: the policy's preprocessing,
    # sampling and values, and the loop's bookkeeping).
    seconds: dict[str, float] = field(default_factory=dict)

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
            seconds={k: sum(p.seconds.get(k, 0.0) for p in parts) for k in parts[0].seconds},
        )


def stack_observations(observations: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {key: np.stack([o[key] for o in observations]) for key in observations[0]}


def derived_seed(*keys: int) -> int:
    """A 31-bit seed from non-negative integer keys: the same keys give the same seed in any process or machine."""
    return int(np.random.SeedSequence(keys).generate_state(1)[0] >> 1)


EPISODE_SEEDS, ACTION_SEEDS, NOISE_SEEDS = 0, 1, 2  # the first key after the worker's seed: which stream it feeds
NOISE_STEPS_WITHOUT_TIME_LIMIT = 1000  # colored noise's sequence length for an env with no `max_episode_steps`


class RolloutWorker:
    """`n_envs` env copies and one agent. Envs keep running across `collect` calls (episodes span rollouts).

    Env i's n-th episode is seeded with `derived_seed(seed, EPISODE_SEEDS, i, n)`, the actions of the k-th `collect`
    come from torch's RNG seeded with `derived_seed(seed, ACTION_SEEDS, k)`: the same weights give the same
    trajectories, and `reseed` puts a replacement worker where a dead one stood. With `noise_color_beta` > 0 the
    Gaussian part of the actions is driven by colored noise instead (rl/colored_noise.py), one sequence per env and
    episode from `derived_seed(seed, NOISE_SEEDS, i, n)`.
    """

    def __init__(self, make_env: Callable[[], gym.Env], make_agent: Callable[[], Agent], n_envs: int,
                 seed: int, make_eval_env: Callable[[], gym.Env] | None = None, noise_color_beta: float = 0.0):
        self.agent = make_agent()
        self.seed = seed
        self.noise_color_beta = noise_color_beta
        self.noise: list[ColoredNoiseStream | None] = [None] * n_envs
        self.envs = [make_env() for _ in range(n_envs)]
        self.make_eval_env = make_eval_env or make_env  # e.g. one that logs its episodes to rerun
        self.eval_env: gym.Env | None = None
        self.reseed(0, [0] * n_envs)

    def reseed(self, iteration: int, episodes_done: list[int]) -> None:
        """Start env i on its episode `episodes_done[i]` (reset from that episode's seed) and the next `collect` on
        iteration `iteration`'s actions. An iteration that starts on episode boundaries is then collected exactly as
        the worker that died in it would have; an episode the dead worker was in the middle of starts again."""
        self.iteration = iteration
        self.episode_index = [int(n) for n in episodes_done]
        self.observations, self.running = [], []
        for i in range(len(self.envs)):
            obs, stats = self._reset(i)
            self.observations.append(obs)
            self.running.append(stats)

    def _reset(self, env_index: int) -> tuple[dict[str, np.ndarray], EpisodeStats]:
        episode_seed = derived_seed(self.seed, EPISODE_SEEDS, env_index, self.episode_index[env_index])
        obs, _ = self.envs[env_index].reset(seed=episode_seed)
        if self.noise_color_beta > 0:
            spec = self.envs[env_index].spec
            horizon = (spec and spec.max_episode_steps) or NOISE_STEPS_WITHOUT_TIME_LIMIT
            noise_seed = derived_seed(self.seed, NOISE_SEEDS, env_index, self.episode_index[env_index])
            self.noise[env_index] = ColoredNoiseStream(self.noise_color_beta, self.agent.noise_dims, horizon,
                                                       np.random.default_rng(noise_seed))
        return flatten_observation(obs), EpisodeStats(0.0, 0, False, None, seed=episode_seed)

    def _exploration_noise(self) -> torch.Tensor | None:
        """This step's colored noise of every env (n_envs, noise_dims); None: the agent draws white noise."""
        if self.noise_color_beta <= 0:
            return None
        return torch.from_numpy(np.stack([stream.next() for stream in self.noise]))

    def _load(self, state_dict: dict[str, torch.Tensor] | None) -> None:
        if state_dict is not None:
            self.agent.load_state_dict(state_dict)

    @contextlib.contextmanager
    def _own_rng(self):
        """Torch's RNG on this iteration's seed, the caller's left as it was: several workers in one process draw
        the same actions as the same workers in separate processes."""
        outer_rng = torch.get_rng_state()
        torch.manual_seed(derived_seed(self.seed, ACTION_SEEDS, self.iteration))
        try:
            yield
        finally:
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
        env_s, render_before = 0.0, self._render_seconds()
        start = time.perf_counter()
        for t in range(steps_per_env):
            raw_obs = stack_observations(self.observations)
            obs_batch = self.agent.observation_batch(raw_obs)
            actions, log_probs, values = self.agent.sample(obs_batch, self._exploration_noise())
            obs_steps.append(raw_obs)
            action_steps.append(actions.numpy())
            log_prob_steps.append(log_probs.numpy())
            value_steps.append(values.numpy())
            env_actions = self.agent.to_env_action(actions).numpy()
            for i, env in enumerate(self.envs):
                step_start = time.perf_counter()
                obs, reward, terminated, truncated, info = env.step(env_actions[i])
                env_s += time.perf_counter() - step_start
                self.running[i].record_step(reward, info)
                rewards[t, i] = reward
                obs = flatten_observation(obs)
                if terminated or truncated:
                    if truncated and not terminated:  # time limit: bootstrap from the state we stopped in
                        last_obs = self.agent.observation_batch(stack_observations([obs]))
                        truncation_values[t, i] = float(self.agent.value(last_obs)[0])
                    dones[t, i] = 1.0
                    finished.append(self.running[i])
                    self.episode_index[i] += 1
                    reset_start = time.perf_counter()
                    obs, self.running[i] = self._reset(i)
                    env_s += time.perf_counter() - reset_start
                self.observations[i] = obs
        last_values = self.agent.value(self.agent.observation_batch(stack_observations(self.observations)))
        self.iteration += 1
        rendering_s = self._render_seconds() - render_before
        seconds = {"policy": time.perf_counter() - start - env_s, "simulation": env_s - rendering_s,
                   "rendering": rendering_s}
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
            seconds=seconds,
        )

    def _render_seconds(self) -> float:
        """The envs' camera time so far (`LiftEnv.render_s`; 0 for envs that do not count it)."""
        return sum(getattr(env.unwrapped, "render_s", 0.0) for env in self.envs)

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

    restarts: int  # workers replaced so far (died or hung)

    def collect(self, state_dict: dict[str, torch.Tensor], steps_per_env: int) -> Trajectories: ...
    def evaluate(self, state_dict: dict[str, torch.Tensor], seeds: list[int],
                 annotations: dict[str, float] | None = None) -> list[EpisodeStats]: ...
    def close(self) -> None: ...


def split_evenly(items: list, n_parts: int) -> list[list]:
    return [items[i::n_parts] for i in range(n_parts)]


class InlineWorkers:
    """The workers in this process, one after the other (tests, debugging, a single core)."""

    restarts = 0

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


class RestartingWorkers:
    """What the process and Ray pools share: every call goes to all workers at once and is awaited until a deadline;
    a worker that died (SIGKILL, segfault, out of memory, an exception) or gave no answer in `timeout_s` (killed) is
    replaced, re-seeded where it stood (`RolloutWorker.reseed`), and its part of the call made again. A worker that
    fails `max_failures` calls in a row stops the run. A backend starts, calls and awaits workers by index."""

    def __init__(self, worker_kwargs: list[dict], timeout_s: float, max_failures: int):
        self.worker_kwargs, self.timeout_s, self.max_failures = worker_kwargs, timeout_s, max_failures
        self.iteration = 0  # collects so far: where a replacement resumes
        self.episodes_done = [np.zeros(kwargs["n_envs"], np.int64) for kwargs in worker_kwargs]
        self.failures_in_a_row = [0] * len(worker_kwargs)
        self.restarts = 0
        self.start_timeout_s = max(timeout_s, START_TIMEOUT_S)
        for index in range(len(worker_kwargs)):
            self._launch(index)
        _, failures = self._gather(range(len(worker_kwargs)), self.start_timeout_s)
        for index, cause in failures.items():
            self._replace(index, cause, "start")

    def _launch(self, index: int) -> None:  # start worker `index` (again); its readiness is its next answer
        raise NotImplementedError

    def _submit(self, index: int, command: str, args: tuple) -> None:
        raise NotImplementedError

    def _gather(self, indices, timeout_s: float) -> tuple[dict[int, object], dict[int, str]]:
        """The next answer of each worker in `indices`, and for those that gave none, what happened to them (the
        hung ones killed)."""
        raise NotImplementedError

    def _shared(self, state_dict: dict[str, torch.Tensor]):  # the weights as every worker receives them
        return {k: v.detach().cpu() for k, v in state_dict.items()}

    def _replace(self, index: int, cause: str, command: str) -> None:
        while cause is not None:
            self.failures_in_a_row[index] += 1
            what = f"rollout worker {index} {cause} during {command} at iteration {self.iteration}"
            if self.failures_in_a_row[index] >= self.max_failures:
                raise RuntimeError(
                    f"{what}: {self.failures_in_a_row[index]} failures in a row, stopping (its traceback, if it raised "
                    "one, is above). Continue the run from its last checkpoint with --resume=true."
                ) from None
            logger.warning(f"{what}; replacing it (its envs re-seeded where they stood) and repeating its {command}")
            self.restarts += 1
            self._launch(index)
            cause = self._gather([index], self.start_timeout_s)[1].get(index)
            if cause is None:
                self._submit(index, "reseed", (self.iteration, self.episodes_done[index].tolist()))
                cause = self._gather([index], self.start_timeout_s)[1].get(index)

    def _call_all(self, command: str, per_worker_args: list[tuple]) -> list:
        for index, args in enumerate(per_worker_args):
            self._submit(index, command, args)
        results, failures = self._gather(range(len(per_worker_args)), self.timeout_s)
        while failures:
            for index, cause in failures.items():
                self._replace(index, cause, command)
                self._submit(index, command, per_worker_args[index])
            answered, failures = self._gather(list(failures), self.timeout_s)
            results.update(answered)
        self.failures_in_a_row = [0] * len(per_worker_args)
        return [results[index] for index in range(len(per_worker_args))]

    def collect(self, state_dict, steps_per_env):
        shared = self._shared(state_dict)
        parts = self._call_all("collect", [(shared, steps_per_env)] * len(self.worker_kwargs))
        for episodes_done, part in zip(self.episodes_done, parts):
            episodes_done += part.dones.sum(axis=0).astype(np.int64)
        self.iteration += 1
        return Trajectories.concatenate(parts)

    def evaluate(self, state_dict, seeds, annotations=None):
        shared = self._shared(state_dict)
        parts = self._call_all(
            "evaluate",
            [(shared, part, annotations) for part in split_evenly(list(seeds), len(self.worker_kwargs))],
        )
        return [e for part in parts for e in part]


def _exit_description(exitcode: int | None) -> str:
    if exitcode is None or exitcode >= 0:
        return f"exit code {exitcode}"
    name = signal.Signals(-exitcode).name
    return f"exit code {exitcode} ({name}: out of memory?)" if name == "SIGKILL" else f"exit code {exitcode} ({name})"


class ProcessWorkers(RestartingWorkers):
    """One `RolloutWorker` per subprocess (spawned: safe with MuJoCo's EGL and torch threads)."""

    def __init__(self, worker_kwargs: list[dict], timeout_s: float = WORKER_TIMEOUT_S,
                 max_failures: int = MAX_WORKER_FAILURES):
        self.context = mp.get_context("spawn")
        self.connections: list = [None] * len(worker_kwargs)
        self.processes: list = [None] * len(worker_kwargs)
        super().__init__(worker_kwargs, timeout_s, max_failures)

    def _launch(self, index):
        if self.processes[index] is not None:  # the one it replaces: dead, or killed as hung
            self.processes[index].kill()
            self.processes[index].join()
            self.connections[index].close()
        parent, child = self.context.Pipe()
        process = self.context.Process(target=_worker_main, args=(child, self.worker_kwargs[index]), daemon=True)
        process.start()
        child.close()  # the worker's end lives in the worker only: its death reads as end of file here
        self.connections[index], self.processes[index] = parent, process

    def _submit(self, index, command, args):
        with contextlib.suppress(BrokenPipeError, ConnectionResetError):  # dead: `_gather` reads its end of file
            self.connections[index].send((command, args))

    def _gather(self, indices, timeout_s):
        deadline = time.monotonic() + timeout_s
        waiting = {self.connections[index]: index for index in indices}
        results, failures = {}, {}
        while waiting:
            ready = mp_connection.wait(list(waiting), timeout=max(deadline - time.monotonic(), 0))
            if not ready:
                for index in waiting.values():
                    self.processes[index].kill()
                    failures[index] = f"(pid {self.processes[index].pid}) gave no answer in {timeout_s:g} s, killed"
                break
            for connection in ready:
                index = waiting.pop(connection)
                try:
                    results[index] = connection.recv()
                except (EOFError, ConnectionResetError):
                    process = self.processes[index]
                    process.join(timeout=5)
                    failures[index] = f"(pid {process.pid}) died with {_exit_description(process.exitcode)}"
        return results, failures

    def close(self):
        for connection in self.connections:
            with contextlib.suppress(BrokenPipeError, OSError):
                connection.send(("close", ()))
        for process in self.processes:
            process.join(timeout=10)
            if process.is_alive():
                process.terminate()


def _ray():
    try:
        import ray
    except ImportError:
        raise ImportError("--rollout.backend=ray needs Ray: pip install '.[ray]'") from None
    return ray


def _run_in_actor(worker: RolloutWorker, command: str | None, *args) -> tuple[str, object]:
    """`worker.command(*args)` (None: nothing, the actor is up) and the id of the process it ran in, which is new
    after Ray restarted the actor."""
    import ray

    return ray.get_runtime_context().get_worker_id(), None if command is None else getattr(worker, command)(*args)


class RayWorkers(RestartingWorkers):
    """One `RolloutWorker` per Ray actor (one CPU each), on the cluster at `address` or on a Ray started here. The
    weights go into Ray's object store once per call; Ray restarts a dead actor (`max_restarts`), on another node
    where its node was lost, and a hung one is killed into a restart. Every answer names the process it came from:
    an actor Ray restarted between two calls (its envs back at their start) is re-seeded like one that died in a
    call."""

    def __init__(self, worker_kwargs: list[dict], address: str | None = None, timeout_s: float = WORKER_TIMEOUT_S,
                 max_failures: int = MAX_WORKER_FAILURES):
        if (address is None or address.startswith("127.0.0.1:")) and "ray" not in sys.modules:
            # Ray resolves 127.0.0.1 to the machine's address and listens on every interface unless multi-node
            # support is off: a Ray only this run uses stays on loopback, and a loopback cluster
            # (loopback_cluster.py) is found at 127.0.0.1.
            os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
        ray = _ray()
        self.started_ray = not ray.is_initialized()
        if self.started_ray:
            # "local": a new Ray even where `ray start` left one running, which `ray.init()` would join
            local = {"address": "local", "num_cpus": max(os.cpu_count() or 1, len(worker_kwargs)),
                     "_node_ip_address": "127.0.0.1", "include_dashboard": False}
            ray.init(**({"address": address} if address else local))
        # SPREAD: over the cluster's nodes, so that losing one node loses few workers; Ray restarts those elsewhere
        actor_class = ray.remote(num_cpus=1, max_restarts=-1, scheduling_strategy="SPREAD")(RolloutWorker)
        # Put in the object store and held by the pool: Ray restarts an actor from its creation arguments, and frees
        # a large one it stored itself once the first start has read it ("already deleted by reference counting").
        self.arguments = [{name: ray.put(value) for name, value in kwargs.items()} for kwargs in worker_kwargs]
        self.actors = [actor_class.remote(**arguments) for arguments in self.arguments]
        self.pending: list = [None] * len(worker_kwargs)
        self.incarnations: list[str | None] = [None] * len(worker_kwargs)  # the process each actor answered from
        super().__init__(worker_kwargs, timeout_s, max_failures)

    def _launch(self, index):
        """Ray starts (and restarts) the actor; asked while it restarts, it answers once it is up (the retries)."""
        self.incarnations[index] = None  # its next answer says which process it is
        self.pending[index] = self.actors[index].__ray_call__.options(max_task_retries=-1).remote(
            _run_in_actor, None)

    def _submit(self, index, command, args):
        # the arguments one by one: Ray hands an actor the objects behind top-level references only (the weights)
        self.pending[index] = self.actors[index].__ray_call__.remote(_run_in_actor, command, *args)

    def _shared(self, state_dict):
        return _ray().put(super()._shared(state_dict))

    def _gather(self, indices, timeout_s):
        ray = _ray()
        waiting = {self.pending[index]: index for index in indices}
        ready, not_ready = ray.wait(list(waiting), num_returns=len(waiting), timeout=timeout_s)
        results, failures = {}, {}
        for ref in ready:
            index = waiting[ref]
            try:
                incarnation, answer = ray.get(ref)
            except ray.exceptions.RayTaskError as error:
                failures[index] = f"raised {type(error.cause).__name__}: {error.cause}"
            except ray.exceptions.RayError as error:
                failures[index] = f"died ({type(error).__name__}: {str(error).splitlines()[0]})"
            else:
                self.incarnations[index] = self.incarnations[index] or incarnation
                if incarnation == self.incarnations[index]:
                    results[index] = answer
                else:
                    failures[index] = "was restarted by Ray since its last answer (its process or node lost)"
        for ref in not_ready:
            ray.kill(self.actors[waiting[ref]], no_restart=False)
            failures[waiting[ref]] = f"gave no answer in {timeout_s:g} s, killed"
        return results, failures

    def close(self):
        ray = _ray()
        for actor in self.actors:
            ray.kill(actor)
        if self.started_ray:
            ray.shutdown()


def make_workers(worker_kwargs: list[dict], n_workers: int, backend: str = "process", ray_address: str | None = None,
                 timeout_s: float = WORKER_TIMEOUT_S, max_failures: int = MAX_WORKER_FAILURES) -> RolloutWorkers:
    """`backend="process"`: one subprocess per entry of `worker_kwargs`, or all inline with `n_workers = 0`;
    `"ray"`: one Ray actor each."""
    if backend == "ray":
        return RayWorkers(worker_kwargs, ray_address, timeout_s, max_failures)
    if n_workers == 0:
        return InlineWorkers(worker_kwargs)
    return ProcessWorkers(worker_kwargs, timeout_s, max_failures)


def make_gym_env(gym_id: str, gym_kwargs: dict) -> gym.Env:
    """A picklable env factory (use with functools.partial)."""
    import lerobot_bcrl.envs  # noqa: F401  (registers gym_bcrl_lift)

    return gym.make(gym_id, disable_env_checker=True, **gym_kwargs)
