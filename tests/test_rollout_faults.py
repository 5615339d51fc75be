"""The rollout backends (subprocesses, Ray actors) give the same trajectories, and survive a worker that dies
(SIGKILL, segfault, abort) or hangs: it is replaced, re-seeded where it stood, and its part collected again; a
worker that keeps dying stops the run with one line. Real worker processes, real faults."""

from __future__ import annotations

import contextlib
import csv
import ctypes
import json
import logging
import os
import re
import signal
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np
import pytest
from policy_fixtures import lowdim_dataset_root  # noqa: F401
from safetensors.torch import load_file
from test_rl_learns import MLPAgent, ReachOrigin

from lerobot_bcrl.rl.rollout import InlineWorkers, RolloutWorker, Trajectories, make_workers

BIN = Path(sys.executable).parent
EPISODE_STEPS = 20  # ReachOrigin's time limit


class FaultyReachOrigin(ReachOrigin):
    """ReachOrigin whose `at_step`-th step (counted from the env's construction) hangs, segfaults or aborts while
    the file `trigger` exists; `once` removes the file first, so that the replacement worker runs clean."""

    def __init__(self, fault: str, at_step: int, trigger: str, once: bool = True):
        self.fault, self.at_step, self.trigger, self.once = fault, at_step, trigger, once
        self.steps = 0

    def step(self, action):
        self.steps += 1
        if self.steps == self.at_step and os.path.exists(self.trigger):
            if self.once:
                os.remove(self.trigger)
            if self.fault == "hang":
                time.sleep(3600)
            elif self.fault == "segfault":
                ctypes.string_at(0)
            else:
                os.abort()
        return super().step(action)


def worker_kwargs(n_workers: int = 2, faulty: dict | None = None) -> list[dict]:
    """Two workers of one env each; worker 0 with a `FaultyReachOrigin(**faulty)`."""
    return [{"make_env": partial(FaultyReachOrigin, **faulty) if faulty and i == 0 else ReachOrigin,
             "make_agent": MLPAgent, "n_envs": 1, "seed": 11 + i} for i in range(n_workers)]


def collect_iterations(workers, n_iterations: int, steps_per_env: int) -> list[Trajectories]:
    state = MLPAgent().module.state_dict()
    try:
        return [workers.collect(state, steps_per_env) for _ in range(n_iterations)]
    finally:
        workers.close()


def assert_same(a: list[Trajectories], b: list[Trajectories]) -> None:
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.observations["obs"], y.observations["obs"])
        np.testing.assert_array_equal(x.actions, y.actions)
        np.testing.assert_array_equal(x.rewards, y.rewards)
        np.testing.assert_array_equal(x.last_values, y.last_values)


@pytest.fixture(scope="module")
def ray_session():
    ray = pytest.importorskip("ray")
    tests = str(Path(__file__).parent)  # the actors unpickle this module's envs and agent
    ray.init(address="local", num_cpus=2, _node_ip_address="127.0.0.1", include_dashboard=False,
             runtime_env={"env_vars": {"PYTHONPATH": os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")])}})
    yield ray
    ray.shutdown()


@pytest.fixture(params=["process", "ray"])
def backend(request) -> str:
    if request.param == "ray":
        request.getfixturevalue("ray_session")
    return request.param


def test_ray_process_and_inline_workers_return_identical_trajectories(ray_session):
    """Same seeds and weights, same trajectories and evaluations on every backend: a run can move between them."""
    state = MLPAgent().module.state_dict()
    kwargs = [{"make_env": ReachOrigin, "make_agent": MLPAgent, "n_envs": 2, "seed": 3 + i} for i in range(2)]
    seeds = [10, 11, 12]
    outcomes = {}
    for backend in ("inline", "process", "ray"):
        workers = make_workers(kwargs, 0 if backend == "inline" else 2, "ray" if backend == "ray" else "process")
        try:
            outcomes[backend] = ([workers.collect(state, 25) for _ in range(2)],  # the second starts mid-episode
                                 [e.episode_return for e in workers.evaluate(state, seeds, {"theta_t": 0.5})])
        finally:
            workers.close()
    for backend in ("process", "ray"):
        assert_same(outcomes["inline"][0], outcomes[backend][0])
        assert outcomes["inline"][1] == outcomes[backend][1]


def test_a_dead_and_a_hung_worker_are_replaced_and_the_run_unchanged_on_whole_episodes(backend, tmp_path, caplog):
    """Worker 0 segfaults in the second of three iterations of whole episodes, worker 1 hangs in the third. Each
    replacement starts its iteration from the same episode seeds and action seeds as the worker it replaces, so
    the three iterations equal an unfaulted run's."""
    segfault, hang = tmp_path / "segfault", tmp_path / "hang"
    segfault.touch(), hang.touch()
    kwargs = worker_kwargs(faulty={"fault": "segfault", "at_step": EPISODE_STEPS + 5, "trigger": str(segfault)})
    kwargs[1]["make_env"] = partial(FaultyReachOrigin, "hang", 2 * EPISODE_STEPS + 5, str(hang))
    workers = make_workers(kwargs, 2, backend, timeout_s=3)
    with caplog.at_level(logging.WARNING, logger="lerobot_bcrl.rl.rollout"):
        faulted = collect_iterations(workers, 3, EPISODE_STEPS)
    assert workers.restarts == 2 and not segfault.exists() and not hang.exists()
    died, hung = caplog.messages
    assert died.startswith("rollout worker 0 ") and "during collect at iteration 1; replacing it" in died
    assert hung.startswith("rollout worker 1 ")
    assert "gave no answer in 3 s, killed during collect at iteration 2" in hung
    if backend == "process":
        assert "died with exit code -11 (SIGSEGV)" in died
    assert_same(collect_iterations(InlineWorkers(worker_kwargs()), 3, EPISODE_STEPS), faulted)


def test_a_ray_actor_restarted_between_two_collects_is_reseeded_where_it_stood(ray_session, caplog):
    """Ray restarts a dead actor by itself (`max_restarts`), so one killed between two calls answers the next from
    fresh envs; the pool sees the new process, re-seeds it where it stood, and both iterations (whole episodes)
    equal an unfaulted run's."""
    ray = ray_session
    unfaulted = collect_iterations(InlineWorkers(worker_kwargs()), 2, 2 * EPISODE_STEPS)  # = Ray's (test above)
    workers = make_workers(worker_kwargs(), 2, "ray")
    state = MLPAgent().module.state_dict()
    try:
        first = workers.collect(state, 2 * EPISODE_STEPS)
        os.kill(ray.get(workers.actors[0].__ray_call__.remote(lambda worker: os.getpid())), signal.SIGKILL)
        ray.get(workers.actors[0].__ray_ready__.options(max_task_retries=-1).remote(), timeout=120)  # restarted
        with caplog.at_level(logging.WARNING):
            second = workers.collect(state, 2 * EPISODE_STEPS)
    finally:
        workers.close()
    assert_same(unfaulted, [first, second])
    assert workers.restarts == 1
    assert "rollout worker 0 was restarted by Ray since its last answer" in caplog.text


def test_a_worker_reseeded_in_the_middle_of_an_episode_starts_that_episode_again():
    """Iterations of 15 steps on 20-step episodes: a replacement for the second iteration resets each env to the
    episode it was 15 steps into (same seed, same first observation) and plays it from the start."""
    state = MLPAgent().module.state_dict()
    worker = RolloutWorker(ReachOrigin, MLPAgent, n_envs=2, seed=11)
    first, second = worker.collect(state, 15), worker.collect(state, 15)
    replacement = RolloutWorker(ReachOrigin, MLPAgent, n_envs=2, seed=11)
    replacement.reseed(1, [0, 0])
    again = replacement.collect(state, 15)
    np.testing.assert_array_equal(again.observations["obs"][0], first.observations["obs"][0])
    assert second.dones.sum() == 2 and again.dones.sum() == 0  # the episodes start again instead of ending


def test_a_worker_that_keeps_dying_stops_the_run_with_one_clear_line(backend, tmp_path):
    trigger = tmp_path / "abort"
    trigger.touch()
    faulty = {"fault": "abort", "at_step": 3, "trigger": str(trigger), "once": False}
    workers = make_workers(worker_kwargs(faulty=faulty), 2, backend, max_failures=2)
    with pytest.raises(RuntimeError) as raised:
        collect_iterations(workers, 1, 10)
    message = str(raised.value)
    assert "\n" not in message and workers.restarts == 1
    assert message.startswith("rollout worker 0 ") and "during collect at iteration 0: 2 failures in a row" in message
    assert message.endswith("Continue the run from its last checkpoint with --resume=true.")
    if backend == "process":
        assert "died with exit code -6 (SIGABRT)" in message


def _descendants(pid: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, IndexError):
            parent = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            children.setdefault(parent, []).append(int(stat.parent.name))
    found, frontier = [], [pid]
    while frontier:
        below = children.get(frontier.pop(), [])
        found += below
        frontier += below
    return found


# 127.0.0.1, ::1 and ::ffff:127.0.0.1 as /proc/net/tcp{,6} write them
LOOPBACK = {"0100007F", "00000000000000000000000001000000", "0000000000000000FFFF00000100007F"}


def listening_addresses(pids: list[int]) -> set[str]:
    """The local addresses on which the processes `pids` listen for TCP connections (/proc/net/tcp's hex)."""
    sockets = set()
    for pid in pids:
        with contextlib.suppress(OSError):
            for fd in Path(f"/proc/{pid}/fd").iterdir():
                with contextlib.suppress(OSError):
                    link = os.readlink(fd)
                    if link.startswith("socket:["):
                        sockets.add(link[len("socket:["):-1])
    addresses = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for fields in (line.split() for line in Path(table).read_text().splitlines()[1:]):
            if fields[3] == "0A" and fields[9] in sockets:  # 0A: LISTEN
                addresses.add(fields[1].rsplit(":", 1)[0])
    return addresses


def rollout_worker_pids(parent_pid: int, backend: str) -> list[int]:
    """The rollout workers below `parent_pid` (a run, or a Ray node)."""
    pids = []
    for pid in set(_descendants(parent_pid)):
        with contextlib.suppress(OSError):
            command = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
            if ("spawn_main" in command) if backend == "process" else command.startswith("ray::RolloutWorker"):
                pids.append(pid)
    return pids


def finetune_args(dataset_root: Path, output_dir: Path, backend: str) -> list[str]:
    """Ten iterations of one whole 40-step episode in each of two workers."""
    return [f"--dataset.repo_id=local/{dataset_root.name}", f"--dataset.root={dataset_root}",
            "--env.type=bcrl_lift", "--env.episode_length=40", "--total_env_steps=800", "--policy.type=bcrl",
            "--policy.push_to_hub=false", f"--rollout.backend={backend}", "--rollout.n_workers=2",
            "--rollout.envs_per_worker=1", "--rollout.steps_per_env=40", "--ppo.minibatch_size=40",
            "--bc_batch_size=16", "--ppo.update_epochs=1", "--save_freq=800", "--eval_freq=0",
            "--final_eval_episodes=2", "--tensorboard=false", f"--output_dir={output_dir}"]


@pytest.fixture(scope="module")
def unfaulted_run(lowdim_dataset_root, tmp_path_factory) -> Path:
    output_dir = tmp_path_factory.mktemp("unfaulted")
    subprocess.run([str(BIN / "bcrl-finetune"), *finetune_args(lowdim_dataset_root, output_dir, "process")],
                   check=True, capture_output=True, timeout=300, env=os.environ.copy())
    return output_dir


def run_with_a_fault(args: list[str], output_dir: Path, fault) -> str:
    """`bcrl-finetune args`, with `fault(run)` once its first iteration is logged (the workers are running); its
    output, the run having ended with exit code 0."""
    run = subprocess.Popen([str(BIN / "bcrl-finetune"), *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True, env=os.environ.copy())
    try:
        logs = output_dir / "logs.csv"
        deadline = time.time() + 300
        logged = lambda: logs.exists() and len(logs.read_text().splitlines()) > 1  # noqa: E731
        while run.poll() is None and time.time() < deadline and not logged():
            time.sleep(0.1)
        assert run.poll() is None, "the run ended before its first iteration was logged"
        fault(run)
        output, _ = run.communicate(timeout=300)
    finally:
        run.kill()
    assert run.returncode == 0, output[-3000:]
    return output


def assert_replaced_once_and_unchanged(output: str, output_dir: Path, unfaulted_run: Path) -> str:
    """One worker replaced during a collect, logged, and the weights and final evaluation of the unfaulted run."""
    (warning,) = [line for line in output.splitlines() if "replacing it" in line]
    assert re.search(r"rollout worker [01] .* during collect at iteration \d+; replacing it", warning), warning
    rows = list(csv.DictReader((output_dir / "logs.csv").open()))
    assert [int(r["env_steps"]) for r in rows] == list(range(80, 801, 80))
    assert int(rows[-1]["worker_restarts"]) == 1
    weights = "checkpoints/last/pretrained_model/model.safetensors"
    faulted = load_file(output_dir / weights)
    for name, tensor in load_file(unfaulted_run / weights).items():
        np.testing.assert_array_equal(tensor.numpy(), faulted[name].numpy(), err_msg=name)
    results = [json.loads((run_dir / "eval_final.json").read_text()) for run_dir in (output_dir, unfaulted_run)]
    assert len(results[0]["episodes"]) == 2 and results[0]["episodes"] == results[1]["episodes"]
    return warning


@pytest.mark.slow
def test_bcrl_finetune_goes_on_after_a_worker_is_killed(lowdim_dataset_root, unfaulted_run, tmp_path):
    """kill -9 of one rollout worker of a running bcrl-finetune (the default process backend): the run replaces it,
    logs it and finishes with the weights and final evaluation of an unfaulted run (its iterations hold whole
    episodes). Under Ray the same runs through the lost-node test below and the library-level tests above."""

    def kill_a_worker(run):
        workers = rollout_worker_pids(run.pid, "process")
        assert len(workers) == 2, workers
        os.kill(workers[0], signal.SIGKILL)

    output = run_with_a_fault(finetune_args(lowdim_dataset_root, tmp_path, "process"), tmp_path, kill_a_worker)
    warning = assert_replaced_once_and_unchanged(output, tmp_path, unfaulted_run)
    assert "died with exit code -9 (SIGKILL: out of memory?)" in warning


@pytest.mark.slow
def test_bcrl_finetune_goes_on_after_a_ray_node_is_lost(lowdim_dataset_root, unfaulted_run, tmp_path):
    """A Ray cluster of three nodes of 1 CPU each on loopback (`ray start --head`, then `ray start --address=...`
    twice) that bcrl-finetune joins with --rollout.ray_address, all of it listening on loopback only. Its two actors
    of 1 CPU each cannot share a node, so at least one runs off the head, whenever each node's resources reach the
    scheduler. That node is lost (its raylet, its actor and every other process of it SIGKILLed at once): Ray
    restarts the actor on the node left free, the run re-seeds it where it stood and finishes with the unfaulted
    run's weights and final evaluation."""
    pytest.importorskip("ray")
    from lerobot_bcrl.rl.loopback_cluster import LoopbackCluster

    with LoopbackCluster([1, 1, 1]) as cluster:
        args = [*finetune_args(lowdim_dataset_root, tmp_path, "ray"), f"--rollout.ray_address={cluster.address}"]

        def lose_a_node_with_a_worker(run):
            cluster_pids = [pid for node in cluster.nodes for pid in [node.pid, *_descendants(node.pid)]]
            listening = listening_addresses([*cluster_pids, run.pid, *_descendants(run.pid)])
            assert listening and listening <= LOOPBACK, f"Ray listens off loopback: {listening}"
            workers_per_node = [len(rollout_worker_pids(node.pid, "ray")) for node in cluster.nodes]
            assert workers_per_node in ([1, 1, 0], [1, 0, 1], [0, 1, 1]), workers_per_node
            cluster.lose_node(1 if workers_per_node[1] else 2)

        output = run_with_a_fault(args, tmp_path, lose_a_node_with_a_worker)
    warning = assert_replaced_once_and_unchanged(output, tmp_path, unfaulted_run)
    assert "died" in warning, warning


def test_rollout_options_refuse_what_they_cannot_do():
    from lerobot_bcrl.rl.configuration import RolloutConfig

    with pytest.raises(ValueError, match=r"--rollout.backend='dask': choose one of \('process', 'ray'\)"):
        RolloutConfig(backend="dask")
    with pytest.raises(ValueError, match="give --rollout.n_workers >= 1"):
        RolloutConfig(backend="ray", n_workers=0)
    with pytest.raises(ValueError, match="--rollout.ray_address is for --rollout.backend=ray"):
        RolloutConfig(ray_address="10.0.0.1:6379")
