"""Riding out a Redis outage: which errors mean "Redis is unreachable", and an exponential back-off.

Shared by the worker's loops and the gateway's stream forwarding: a lost connection is waited out (with capped
back-off and one log line per outage), never a reason to exit or to fail a session.
"""

from __future__ import annotations

import logging
import random
import threading

import redis
from redis.exceptions import ClusterError, RedisClusterException, TryAgainError

# What redis-py raises while the server is down, restarting (LOADING is a BusyLoadingError, a ConnectionError)
# or unreachable; the asyncio client raises the same classes. On a Redis Cluster also while a shard fails over
# (CLUSTERDOWN, too many redirections, nodes that disagree on the slot map or none reachable while the client
# refreshes it: RedisClusterException) or a slot migrates (TRYAGAIN). RedisClusterException also stands for a
# command over keys of several slots, which this code never sends (every multi-key call stays in one session's
# slot, checked against a real cluster by tests/runtime/test_cluster.py).
REDIS_DOWN: tuple[type[Exception], ...] = (redis.ConnectionError, redis.TimeoutError, ClusterError, TryAgainError,
                                           RedisClusterException)


def closed_transport(err: Exception) -> redis.ConnectionError:
    """The ConnectionError for a raw transport error on a connection the server closed (a killed cluster primary):
    uvloop's RuntimeError on a write, which redis-py's asyncio client lets through instead of its own error."""
    return redis.ConnectionError(f"connection closed by the server: {err}")


class Backoff:
    """Delays of `first_s`, doubling up to `max_s`, with +-20 % jitter so a fleet does not reconnect in lockstep."""

    def __init__(self, first_s: float = 0.1, max_s: float = 2.0) -> None:
        if not 0 < first_s <= max_s:
            raise ValueError("need 0 < first_s <= max_s")
        self.first_s = first_s
        self.max_s = max_s
        self.failures = 0

    def next_delay(self) -> float:
        """The delay before the next attempt; each call counts one more failure."""
        delay = min(self.max_s, self.first_s * 2 ** self.failures)
        self.failures += 1
        return delay * random.uniform(0.8, 1.2)

    def reset(self) -> None:
        self.failures = 0


class OutageLog:
    """Logs the start and the end of an outage once each, not every failed attempt."""

    def __init__(self, logger: logging.Logger, what: str) -> None:
        self.logger = logger
        self.what = what
        self.down = False

    def failed(self, err: Exception) -> None:
        if not self.down:
            self.logger.warning("%s: Redis unreachable (%s); retrying with back-off", self.what, err)
            self.down = True

    def recovered(self) -> None:
        if self.down:
            self.logger.warning("%s: Redis reachable again", self.what)
            self.down = False


def wait_for_redis(client: redis.Redis, stop: threading.Event, what: str, logger: logging.Logger,
                   backoff: Backoff | None = None) -> bool:
    """Block until `client` answers PING (True) or `stop` is set (False)."""
    backoff = backoff or Backoff()
    outage = OutageLog(logger, what)
    while not stop.is_set():
        try:
            client.ping()
            outage.recovered()
            return True
        except REDIS_DOWN as err:
            outage.failed(err)
            stop.wait(backoff.next_delay())
    return False
