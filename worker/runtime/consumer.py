"""The worker: takes sessions from the jobs streams (`keys.JOB_STREAMS`, consumer group "workers", read as
`worker.runtime.partitions` says), runs each in a `SessionRunner` thread under a lease, renews its leases by
heartbeats, takes over sessions of dead workers (XAUTOCLAIM of jobs idle longer than the lease TTL) and serves
render/export requests for finished sessions. A session's job always sits in the partition of its id,
`keys.jobs(session_id)`.
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
import zlib
from datetime import datetime

import redis

from protocol import keys
from worker.runtime.archive import BlobStore, archive_finished
from worker.runtime.engine import SessionEngine, close_engine, restore_engine, warm_up
from worker.runtime.leases import Leases, lease_holder
from worker.runtime.memory import over_budget
from worker.runtime.outage import REDIS_DOWN, Backoff, OutageLog, wait_for_redis
from worker.runtime.partitions import PartitionReader
from worker.runtime.record import abandon_unstarted
from worker.runtime.requests import handle_request
from worker.runtime.session_settings import this_machine
from worker.runtime.sessions import RuntimeConfig, SessionRunner, ensure_group
from worker.runtime.snapshots import read_snapshot
from worker.runtime.stats import StageStats

log = logging.getLogger(__name__)

STALE_SCAN_COUNT = 200  # pending jobs per partition looked at for the next stale deadline
STALE_MARGIN_S = 0.01  # past a job's stale deadline: XAUTOCLAIM's idle test must pass by then
WAITING_RETRY_MS = 50  # a claimed session whose old lease is still there is tried again this soon


class Worker:
    """One worker process's runtime. `run()` blocks until `shutdown()` (or SIGTERM in main.py)."""

    def __init__(self, client: redis.Redis, worker_id: str, config: RuntimeConfig) -> None:
        self.client = client
        self.worker_id = worker_id
        self.config = config
        self.leases = Leases(client, worker_id, config.lease_ttl_ms)
        self.stats = StageStats()
        self.runners: dict[str, SessionRunner] = {}
        self._waiting: dict[str, str] = {}  # session id -> job id claimed while the old lease had not expired yet
        self._claimed_at: dict[str, float] = {}  # session id -> wall time its job was claimed from a silent worker
        self._stopping = threading.Event()
        self._next_claim = 0.0
        self._deferred: dict[str, str] = {}  # session id -> job id of sessions created but not streamed yet
        self._next_deferred_check = 0.0
        self.blobs = BlobStore(config.blob_dir) if config.blob_dir else None
        self._finished_engines: collections.OrderedDict[str, SessionEngine] = collections.OrderedDict()
        start = zlib.crc32(worker_id.encode())  # workers start their turns at different partitions
        self._jobs = PartitionReader(keys.JOB_STREAMS, min(config.block_ms, 500), start)
        self._requests = PartitionReader(keys.REQUEST_STREAMS, 500, start)

    # --- lifecycle ----------------------------------------------------------------------------------------------
    def run(self) -> None:
        if not wait_for_redis(self.client, self._stopping, f"worker {self.worker_id} start-up", log):
            return
        warm_up(self.config.engine)  # before taking sessions: a takeover must not wait for imports
        self._ensure_groups()
        self._heartbeat_once()
        threads = [threading.Thread(target=self._heartbeat_loop, name="heartbeat", daemon=True),
                   threading.Thread(target=self._requests_loop, name="requests", daemon=True)]
        if self.blobs is not None and self.config.archive_after_s > 0:
            threads.append(threading.Thread(target=self._archive_loop, name="archive", daemon=True))
        for thread in threads:
            thread.start()
        log.info("worker %s ready (engine %s)", self.worker_id, self.config.engine)
        try:
            self._jobs_loop()
        finally:
            self._stopping.set()
            for runner in list(self.runners.values()):
                runner.stop()
            for runner in list(self.runners.values()):
                runner.join(timeout=30)
            for thread in threads:
                thread.join(timeout=5)
            try:
                self.client.delete(keys.worker(self.worker_id))
            except REDIS_DOWN:
                pass  # the heartbeat key expires on its own
            log.info("worker %s stopped", self.worker_id)

    def shutdown(self) -> None:
        self._stopping.set()

    def _ensure_groups(self) -> None:
        for stream in (*keys.JOB_STREAMS, *keys.REQUEST_STREAMS):
            ensure_group(self.client, stream)

    # --- jobs ---------------------------------------------------------------------------------------------------
    def _jobs_loop(self) -> None:
        """Take jobs until stopped; a Redis outage is waited out with back-off (the process never exits for it)."""
        self._next_claim = 0.0
        backoff = Backoff()
        outage = OutageLog(log, f"worker {self.worker_id}")
        while not self._stopping.is_set():
            try:
                self._jobs_step()
                outage.recovered()
                backoff.reset()
            except REDIS_DOWN as err:
                outage.failed(err)
                self._stopping.wait(backoff.next_delay())
            except redis.ResponseError as err:
                if "NOGROUP" not in str(err):
                    raise
                log.warning("consumer groups missing (Redis restarted without its data?): recreating them")
                self._ensure_groups()

    def _jobs_step(self) -> None:
        self._reap_runners()
        if time.monotonic() >= self._next_claim:
            self._claim_stale_jobs()
            self._next_claim = self._next_stale_at()
        for session_id, job_id in list(self._waiting.items()):
            self._take(session_id, job_id)
        if self._deferred and time.monotonic() >= self._next_deferred_check:
            self._check_deferred()
            self._next_deferred_check = time.monotonic() + 0.5
        if len(self.runners) >= self.config.max_sessions or over_budget(self.config.memory_budget_mb):
            time.sleep(0.05)
            return
        due_ms = WAITING_RETRY_MS if self._waiting else int(1000 * max(0.0, self._next_claim - time.monotonic()))
        for index, (_stream, job_id, fields) in enumerate(self._jobs.read(self.client, self.worker_id,
                                                                          within_ms=due_ms + 1)):
            if index == 0:
                self._take(fields[b"session_id"].decode(), job_id.decode())
            else:  # one job per read, as from a single queue: the others go back for any worker
                self._hand_back(fields[b"session_id"].decode(), job_id.decode())

    def _claim_stale_jobs(self) -> None:
        """Jobs whose owner stopped renewing them (dead worker) for longer than a lease lasts."""
        for stream in keys.JOB_STREAMS:
            start = "0-0"
            while True:
                start, claimed, *_ = self.client.xautoclaim(stream, keys.GROUP, self.worker_id,
                                                            min_idle_time=self.config.lease_ttl_ms, start_id=start,
                                                            count=10)
                for job_id, fields in claimed:
                    if fields:
                        session_id = fields[b"session_id"].decode()
                        if session_id not in self.runners:
                            log.info("claimed the job of session %s from a silent worker", session_id)
                            self._claimed_at[session_id] = time.time()
                            self._take(session_id, job_id.decode())
                    else:  # the entry was trimmed away
                        self.client.xack(stream, keys.GROUP, job_id)
                if start in (b"0-0", "0-0"):
                    break

    def _next_stale_at(self) -> float:
        """When (monotonic) the next job another worker holds goes stale if that worker stays silent: its last
        heartbeat refreshed the job, so it goes stale a lease TTL after that. The jobs loop wakes then, rather than
        polling, so a dead worker's sessions are taken as soon as its lease can have expired."""
        now = time.monotonic()
        ttl_s = self.config.lease_ttl_ms / 1000
        soonest = now + ttl_s / 2  # jobs claimed or taken meanwhile are seen within half a lease
        pipe = self.client.pipeline(transaction=False)
        for stream in keys.JOB_STREAMS:
            pipe.xpending_range(stream, keys.GROUP, min="-", max="+", count=STALE_SCAN_COUNT)
        for pending in pipe.execute():
            for entry in pending:
                consumer = entry["consumer"].decode() if isinstance(entry["consumer"], bytes) else entry["consumer"]
                if consumer != self.worker_id:
                    idle_s = entry["time_since_delivered"] / 1000
                    soonest = min(soonest, now + max(0.0, ttl_s - idle_s) + STALE_MARGIN_S)
        return soonest

    def _take(self, session_id: str, job_id: str) -> None:
        """Own the session if it still needs running and its lease is free."""
        running = self.runners.get(session_id)
        if running is not None and running.is_alive():
            if running.job_id != job_id:  # a duplicate job (a create retried by the client library)
                self.client.xack(keys.jobs(session_id), keys.GROUP, job_id)
            self._waiting.pop(session_id, None)
            return
        status = self.client.hget(keys.session(session_id), "status")
        if status is None or status.decode() in ("finished", "failed", "abandoned"):
            self.client.xack(keys.jobs(session_id), keys.GROUP, job_id)
            self._waiting.pop(session_id, None)
            return
        if status == b"created":  # no frame yet: it takes no slot until one comes (see _check_deferred)
            self._deferred[session_id] = job_id
            self._waiting.pop(session_id, None)
            return
        if (len(self.runners) >= self.config.max_sessions or over_budget(self.config.memory_budget_mb)
                or not self.leases.acquire(session_id)):
            self._waiting[session_id] = job_id  # retried until the old owner's lease expires
            return
        self._waiting.pop(session_id, None)
        self.client.xclaim(keys.jobs(session_id), keys.GROUP, self.worker_id, min_idle_time=0,
                           message_ids=[job_id], justid=True)
        runner = SessionRunner(self.client, self.worker_id, session_id, job_id, self.leases, self.config,
                               self.stats)
        runner.claimed_at = self._claimed_at.pop(session_id, None)
        self.runners[session_id] = runner
        runner.start()
        log.info("session %s started on %s", session_id, self.worker_id)

    def _check_deferred(self) -> None:
        """Sessions waiting for their first frame: taken once it came, dropped once they ended, abandoned when
        none came within the idle timeout. A flood of sessions nobody streams to holds no worker slot."""
        pipe = self.client.pipeline(transaction=False)
        deferred = list(self._deferred.items())
        for session_id, _ in deferred:
            pipe.hmget(keys.session(session_id), ["status", "created_at"])
        now = time.time()
        for (session_id, job_id), (status, created) in zip(deferred, pipe.execute()):
            if status == b"created":
                idle = self.config.idle_timeout_s
                age = now - datetime.fromisoformat(created.decode()).timestamp() if created else 0.0
                if not idle or age < idle or not abandon_unstarted(self.client, session_id, idle,
                                                                   self.config.outbox_maxlen):
                    continue
            del self._deferred[session_id]
            holder = lease_holder(self.client, session_id) if status == b"streaming" else None
            if holder not in (None, self.worker_id):  # the job queued with its first frame runs it elsewhere
                self.client.xack(keys.jobs(session_id), keys.GROUP, job_id)
            elif status == b"streaming" and len(self.runners) >= self.config.max_sessions:
                self._hand_back(session_id, job_id)  # full here: a worker with room reads it at once
            else:
                self._take(session_id, job_id)  # streaming: run it; ended (or just abandoned): ack its job

    def _hand_back(self, session_id: str, job_id: str) -> None:
        """Put a session's job back in the queue as a new entry, for any worker (and ack this one)."""
        pipe = self.client.pipeline(transaction=True)  # one stream: one hash slot, atomic on a cluster too
        pipe.xadd(keys.jobs(session_id), {"session_id": session_id})
        pipe.xack(keys.jobs(session_id), keys.GROUP, job_id)
        pipe.execute()

    def _reap_runners(self) -> None:
        for session_id, runner in list(self.runners.items()):
            if runner.is_alive():
                continue
            del self.runners[session_id]
            if runner.terminal:
                self.client.xack(keys.jobs(session_id), keys.GROUP, runner.job_id)
            elif runner.interrupted:  # Redis went away under it: take the session again once Redis is back
                self._waiting[session_id] = runner.job_id

    # --- heartbeats ---------------------------------------------------------------------------------------------
    def _heartbeat_loop(self) -> None:
        interval = self.config.lease_ttl_ms / 3000
        outage = OutageLog(log, f"worker {self.worker_id} heartbeat")
        while not self._stopping.wait(interval):
            try:
                self._heartbeat_once()
                outage.recovered()
            except REDIS_DOWN as err:
                outage.failed(err)
            except redis.RedisError:
                log.exception("heartbeat failed")

    def _heartbeat_once(self) -> None:
        pipe = self.client.pipeline(transaction=False)
        pipe.set(keys.worker(self.worker_id), len(self.runners), px=self.config.lease_ttl_ms)
        pipe.hset(keys.worker_stats(self.worker_id), mapping=self.stats.as_fields())
        pipe.expire(keys.worker_stats(self.worker_id), 3600)
        if self.config.engine == "slam":
            machine = json.dumps(this_machine(self.config.checkpoint).to_dict())
            pipe.set(keys.worker_machine(self.worker_id), machine, px=self.config.lease_ttl_ms)
        pipe.execute()
        for session_id, runner in list(self.runners.items()):
            if not runner.is_alive():
                continue
            if self.leases.renew(session_id):
                # keep our job entry fresh so XAUTOCLAIM by others only catches jobs of silent workers
                self.client.xclaim(keys.jobs(session_id), keys.GROUP, self.worker_id, min_idle_time=0,
                                   message_ids=[runner.job_id], justid=True)
            else:
                runner.lease_lost()

    # --- the blob store ------------------------------------------------------------------------------------------
    def _archive_loop(self) -> None:
        """Move finished sessions past FLASHMONO_ARCHIVE_AFTER_S to the blob store (any worker; one at a time)."""
        interval = max(1.0, min(60.0, self.config.archive_after_s / 2))
        while not self._stopping.wait(interval):
            try:
                archive_finished(self.client, self.blobs, self.config.archive_after_s)
            except (redis.RedisError, OSError) as err:
                log.warning("archiving failed (retried later): %s", err)

    # --- requests for finished sessions -------------------------------------------------------------------------
    def _requests_loop(self) -> None:
        backoff = Backoff()
        outage = OutageLog(log, f"worker {self.worker_id} requests")
        while not self._stopping.is_set():
            try:
                for stream, entry_id, fields in self._requests.read(self.client, self.worker_id):
                    t0 = time.perf_counter()
                    session_id = fields.get(b"session_id", b"").decode()
                    handle_request(self.client, self._finished_engine(session_id), fields)
                    self.client.xack(stream, keys.GROUP, entry_id)
                    self.stats.add("render", time.perf_counter() - t0)
                outage.recovered()
                backoff.reset()
            except REDIS_DOWN as err:
                outage.failed(err)
                self._stopping.wait(backoff.next_delay())
            except redis.RedisError:
                log.exception("request loop error")
                self._stopping.wait(0.5)

    def _finished_engine(self, session_id: str) -> SessionEngine | None:
        """The engine of a finished session, restored from its snapshot (a small LRU cache)."""
        stored = read_snapshot(self.client, session_id)
        snap = [None, None, None] if stored is None else [stored.stream_id, stored.engine.encode(), stored.data]
        if snap[2] is None and self.blobs is not None:  # archived: the snapshot lives in the blob store
            archived = self.blobs.snapshot(session_id) or {}
            snap = [archived.get(b"stream_id"), archived.get(b"engine"), archived.get(b"data")]
        if snap[2] is None:
            return None
        cache_key = f"{session_id}@{snap[0].decode()}"
        if cache_key in self._finished_engines:
            self._finished_engines.move_to_end(cache_key)
            return self._finished_engines[cache_key]
        engine = restore_engine(snap[1].decode(), snap[2], None if stored is None else stored.chunks)
        self._finished_engines[cache_key] = engine
        while len(self._finished_engines) > 4:
            close_engine(self._finished_engines.popitem(last=False)[1])
        return engine
