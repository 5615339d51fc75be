"""A Ray cluster of several nodes on this machine, bound to loopback only: the path a real cluster takes
(`ray start --head`, `ray start --address=...`, `--rollout.ray_address`) and the loss of a whole node, tried
without a network. The tests and `bench/rollout_throughput.py --ray_cluster` use it.

Every node is a `ray start --block` process at 127.0.0.1 in a session of its own; Ray's servers then listen on
127.0.0.1 only. Ray swaps 127.0.0.1 for the machine's address where
multi-node support is on: the head runs with it off (`RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`), and the nodes that
join (a joining `ray start` refuses to run with it off) run Ray's own CLI with that swap left out. On a real cluster
neither is needed. Unless `RAY_AUTH_MODE` says otherwise, the cluster, and this process and the drivers it starts
while the cluster runs, use Ray's token authentication (the token at ~/.ray/auth_token, made if missing), as a new
local Ray does by default."""

import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

NODE_IP, PORT = "127.0.0.1", 6390
START_TIMEOUT_S = 120.0  # for one node to come up
# `ray start` for a joining node, minus the swap of 127.0.0.1 for the machine's address
JOIN_ON_LOOPBACK = (
    "import sys, ray._private.services as services\n"
    "services.resolve_ip_for_localhost = lambda host: host\n"
    "from ray.scripts.scripts import main\n"
    "sys.argv[0] = 'ray'\n"
    "main()\n"
)
NODE_ENV = {
    # a lost node is noticed in ~2 s instead of Ray's default ~20 s (its health checks, read by the head's GCS)
    "RAY_health_check_initial_delay_ms": "500", "RAY_health_check_period_ms": "500",
    "RAY_health_check_timeout_ms": "1000", "RAY_health_check_failure_threshold": "3",
    "RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S": "0",  # a node told to stop stops (no 30 s drain)
}


class LoopbackCluster:
    """`with LoopbackCluster([1, 1, 1]) as cluster:` a head and two nodes of 1 CPU each at `cluster.address`
    (127.0.0.1:6390); `cluster.lose_node(1)` kills node 1 and every process it started at once (SIGKILL), as a
    machine that vanishes. A driver joins it with `RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0` (`RayWorkers` sets it for a
    127.0.0.1 address), else Ray looks for the cluster at the machine's address."""

    def __init__(self, node_cpus: list[int]):
        self.node_cpus, self.address = node_cpus, f"{NODE_IP}:{PORT}"
        self.env = {**os.environ, **NODE_ENV}
        self.nodes: list[subprocess.Popen] = []
        self.auth_mode_set_here = False

    def __enter__(self) -> "LoopbackCluster":
        with socket.socket() as probe:
            try:
                probe.bind((NODE_IP, PORT))
            except OSError:
                raise RuntimeError(f"{self.address} is taken (a Ray left running? `ray stop`), so no loopback "
                                   "cluster starts there") from None
        if "RAY_AUTH_MODE" not in os.environ:
            # Ray's own switch (ray==2.60.0, pinned in pyproject.toml): the environment variable for this process and
            # its children, and this process's cached Ray config; then a token if there is none
            from ray._private.authentication.authentication_token_setup import (
                _enable_token_auth,
                ensure_token_if_auth_enabled,
            )

            _enable_token_auth()
            ensure_token_if_auth_enabled()
            self.auth_mode_set_here = True
        self.env["RAY_AUTH_MODE"] = os.environ["RAY_AUTH_MODE"]
        common = ["--node-ip-address", NODE_IP, "--disable-usage-stats", "--block"]
        try:
            self._start(["-m", "ray.scripts.scripts", "start", "--head", f"--port={PORT}", "--include-dashboard=false",
                         f"--num-cpus={self.node_cpus[0]}", *common], multi_node=False)
            for cpus in self.node_cpus[1:]:
                self._start(["-c", JOIN_ON_LOOPBACK, "start", f"--address={self.address}", f"--num-cpus={cpus}",
                             *common], multi_node=True)
        except BaseException:
            self.__exit__()
            raise
        return self

    def _start(self, arguments: list[str], multi_node: bool) -> None:
        env = {**self.env, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": str(int(multi_node))}
        with tempfile.TemporaryFile() as output:
            self.nodes.append(subprocess.Popen([sys.executable, *arguments], env=env, start_new_session=True,
                                               stdout=output, stderr=subprocess.STDOUT))
            deadline = time.monotonic() + START_TIMEOUT_S
            while self.alive_nodes() < len(self.nodes):
                if self.nodes[-1].poll() is not None or time.monotonic() > deadline:
                    output.seek(0)
                    last = ([""] + output.read().decode(errors="replace").strip().splitlines())[-1]
                    raise RuntimeError(f"Ray node {len(self.nodes) - 1} of the loopback cluster at {self.address} "
                                       f"did not come up in {START_TIMEOUT_S:g} s: {last}")
                time.sleep(0.5)

    def alive_nodes(self) -> int:
        from ray._raylet import GcsClient
        from ray.core.generated.gcs_pb2 import GcsNodeInfo

        try:
            nodes = GcsClient(address=self.address).get_all_node_info(timeout=5).values()
        except Exception:  # the head's GCS is not up yet (the port was free when the cluster started)
            return 0
        return sum(node.state == GcsNodeInfo.ALIVE for node in nodes)

    def lose_node(self, index: int) -> None:
        os.killpg(self.nodes[index].pid, signal.SIGKILL)
        self.nodes[index].wait()

    def __exit__(self, *exc) -> None:
        for node in reversed(self.nodes):
            if node.poll() is None:
                node.terminate()  # `ray start --block` stops the node's processes
                try:
                    node.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    os.killpg(node.pid, signal.SIGKILL)
                    node.wait()
        # what `ray stop` also removes: else a later `ray.init()` on this machine looks for this cluster
        latest = Path(tempfile.gettempdir()) / "ray" / "ray_current_cluster"
        if latest.exists() and latest.read_text().strip() == self.address:
            latest.unlink()
        if self.auth_mode_set_here:
            os.environ.pop("RAY_AUTH_MODE")
