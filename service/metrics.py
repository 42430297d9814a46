"""Prometheus metrics of the gateway, plus the workers' per-stage latencies read from Redis at scrape time."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from protocol.keys import WORKER_STAGES as STAGES

LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)


class GatewayMetrics:
    """One registry per app instance (tests run several apps in one process)."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.frames_ingested = Counter("flashmono_frames_ingested", "frames accepted into session queues",
                                       registry=r)
        self.frames_refused = Counter("flashmono_frames_refused", "frames refused by the gateway", ["reason"],
                                      registry=r)
        self.ack_latency = Histogram("flashmono_ack_latency_seconds", "frame received to ack sent",
                                     buckets=LATENCY_BUCKETS, registry=r)
        self.queue_depth = Histogram("flashmono_queue_depth", "session queue depth at ingest",
                                     buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256), registry=r)
        self.sessions_created = Counter("flashmono_sessions_created", "sessions created", registry=r)
        self.streams_open = Gauge("flashmono_streams_open", "open WebSocket streams", registry=r)
        self.request_latency = Histogram("flashmono_request_latency_seconds", "render/export round trip",
                                         ["kind"], buckets=LATENCY_BUCKETS, registry=r)
        self._worker_stats: dict[str, dict[str, float]] = {}
        self._workers_alive = 0
        self._sessions_by_status: dict[str, int] = {}
        self.registry.register(_RedisCollector(self))

    def render(self, worker_stats: dict[str, dict[str, float]], workers_alive: int,
               sessions_by_status: dict[str, int]) -> bytes:
        """The text exposition, with the Redis-side figures fetched by the caller just before."""
        self._worker_stats = worker_stats
        self._workers_alive = workers_alive
        self._sessions_by_status = sessions_by_status
        return generate_latest(self.registry)


class _RedisCollector:
    def __init__(self, owner: GatewayMetrics) -> None:
        self.owner = owner

    def collect(self):
        stage_sum = CounterMetricFamily("flashmono_worker_stage_seconds", "worker time per stage (sum)",
                                        labels=["worker", "stage"])
        stage_count = CounterMetricFamily("flashmono_worker_stage_events", "worker events per stage (count)",
                                          labels=["worker", "stage"])
        stage_p99 = GaugeMetricFamily("flashmono_worker_stage_p99_seconds", "p99 over the recent window",
                                      labels=["worker", "stage"])
        for worker, fields in self.owner._worker_stats.items():
            for stage in STAGES:
                stage_sum.add_metric([worker, stage], fields.get(f"{stage}_sum", 0.0))
                stage_count.add_metric([worker, stage], fields.get(f"{stage}_count", 0.0))
                if f"{stage}_p99" in fields:
                    stage_p99.add_metric([worker, stage], fields[f"{stage}_p99"])
        yield stage_sum
        yield stage_count
        yield stage_p99
        yield GaugeMetricFamily("flashmono_workers_alive", "workers with a live heartbeat",
                                value=self.owner._workers_alive)
        sessions = GaugeMetricFamily("flashmono_sessions", "sessions by status", labels=["status"])
        for status, count in sorted(self.owner._sessions_by_status.items()):
            sessions.add_metric([status], count)
        yield sessions
