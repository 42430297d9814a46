"""Connecting to Redis, a single instance or a Redis Cluster, from one URL (REDIS_URL).

A cluster is named by the scheme `redis+cluster://` (`rediss+cluster://` with TLS), with one or more seed nodes:
`redis+cluster://[user:password@]host1:6379,host2:6379`; any seed is enough, the client learns the rest of the
cluster from it. Every other URL (`redis://`, `rediss://`, `unix://`) is a single instance. Both give a client with
the same commands (redis-py's `Redis` or `RedisCluster`), so the gateway and the workers run one code path; where
a cluster needs something else (operations over keys of several sessions) `is_cluster` tells.
"""

from __future__ import annotations

from typing import Any
from urllib.parse import urlsplit, urlunsplit

import redis
import redis.asyncio as aioredis
from redis.asyncio.cluster import ClusterNode as AsyncClusterNode
from redis.asyncio.cluster import RedisCluster as AsyncRedisCluster
from redis.cluster import ClusterNode, RedisCluster

CLUSTER_SCHEMES = {"redis+cluster": "redis", "rediss+cluster": "rediss"}


def is_cluster_url(url: str) -> bool:
    return urlsplit(url).scheme in CLUSTER_SCHEMES


def cluster_seeds(url: str) -> tuple[str, list[tuple[str, int]]]:
    """(a plain redis:// URL of the first seed with the credentials and options, every seed as (host, port))."""
    parts = urlsplit(url)
    if parts.scheme not in CLUSTER_SCHEMES:
        raise ValueError(f"not a cluster URL (redis+cluster://host:port,...): {url!r}")
    credentials, _, hosts = parts.netloc.rpartition("@")
    seeds = []
    for item in filter(None, hosts.split(",")):
        host, _, port = item.rpartition(":") if ":" in item else (item, "", "6379")
        if not host or not port.isdigit():
            raise ValueError(f"cluster seed {item!r} is not host:port in {url!r}")
        seeds.append((host, int(port)))
    if not seeds:
        raise ValueError(f"no seed node in the cluster URL {url!r}")
    if parts.path not in ("", "/", "/0"):
        raise ValueError("a Redis Cluster has only database 0")
    first = f"{credentials}@{seeds[0][0]}:{seeds[0][1]}" if credentials else f"{seeds[0][0]}:{seeds[0][1]}"
    return urlunsplit((CLUSTER_SCHEMES[parts.scheme], first, "", parts.query, "")), seeds


def connect(url: str, **options: Any) -> redis.Redis | RedisCluster:
    """A synchronous client for `url`; `options` go to redis-py (e.g. `retry`, `health_check_interval`)."""
    if is_cluster_url(url):
        plain, seeds = cluster_seeds(url)
        return RedisCluster.from_url(plain, startup_nodes=[ClusterNode(h, p) for h, p in seeds], **options)
    return redis.Redis.from_url(url, **options)


def connect_async(url: str, max_connections: int, **options: Any) -> aioredis.Redis | AsyncRedisCluster:
    """An asyncio client for `url` holding at most `max_connections` connections (per node on a cluster).

    On a single instance the pool blocks a burst of requests until a connection is free (up to 10 s)."""
    if is_cluster_url(url):
        plain, seeds = cluster_seeds(url)
        return AsyncRedisCluster.from_url(plain, startup_nodes=[AsyncClusterNode(h, p) for h, p in seeds],
                                          max_connections=max_connections, **options)
    pool = aioredis.BlockingConnectionPool.from_url(url, max_connections=max_connections, timeout=10, **options)
    return aioredis.Redis(connection_pool=pool)


def is_cluster(client: object) -> bool:
    """Whether `client` (sync or asyncio) talks to a Redis Cluster."""
    return isinstance(client, (RedisCluster, AsyncRedisCluster))


async def close_async(client: aioredis.Redis | AsyncRedisCluster) -> None:
    """Close an asyncio client from `connect_async` and its connections."""
    await client.aclose()
    if not is_cluster(client):
        await client.connection_pool.aclose()
