"""One owned session: restore its snapshot, replay what came after it, then process frames as they arrive.

Delivery guarantees (see DESIGN.md): a frame's input entry is XACKed in the same atomic Lua call that stores its
result (pose record, counters, outbound message), and the store is idempotent by seq (HSETNX), so a frame is
counted once even when a new owner processes it again after a crash. A new owner rebuilds the engine from the
last snapshot and replays every input entry after the snapshot's stream id: frames whose results are already
stored are fed to the engine silently (to rebuild its state); the others are processed normally.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from datetime import UTC, datetime
from typing import Any

import numpy as np
import redis

from protocol import keys
from protocol.codec import pack, unpack
from protocol.messages import (
    INPUT_EVENTS,
    MAP_EVENTS,
    TRACKING_EVENTS,
    DepthMisregistered,
    ErrorCode,
    ErrorMessage,
    FinishedMessage,
    Initializing,
    LoopClosed,
    NewMap,
    PoseMessage,
    PoseSourceChosen,
    ServerMessage,
    SkippedMessage,
    TrackingLost,
)
from protocol.poses import similarity_scale
from worker import events as engine_events
from worker.data.frame import Frame
from worker.pipeline.snapshot_chunks import ChunkWrite
from worker.runtime.engine import SessionEngine, close_engine, create_engine, engine_intrinsics, restore_engine
from worker.runtime.failpoints import failpoint
from worker.runtime.finish_requests import RequestsWhileFinishing
from worker.runtime.frames import FrameError, decode_frame, session_camera
from worker.runtime.leases import Leases
from worker.runtime.map_exchange import MapExchange
from worker.runtime.outage import REDIS_DOWN
from worker.runtime.progress import FinishProgress
from worker.runtime.quarantine import FrameAttempts
from worker.runtime.record import SessionRecord
from worker.runtime.requests import handle_request
from worker.runtime.session_map import extend_stored_map, session_in_map
from worker.runtime.session_settings import named_preset, session_settings, this_machine
from worker.runtime.settings import RuntimeConfig
from worker.runtime.snapshots import SnapshotWriter, read_snapshot
from worker.runtime.stats import StageStats

# The engine's events (worker.events), by their protocol message: TRACKING_EVENTS are forwarded to the clients as
# their own messages and each sets the session's tracking state; INPUT_EVENTS are forwarded (tracking goes on), and
# a misregistration, and device poses that disagree with the images, are also kept in the session record's
# `warnings`; MAP_EVENTS are published with the revision they made, the tracking state staying as it is.
# Events sent as their own messages: one that carries a revision (a pose source's verdict replaying the judged
# frames, a new map's re-estimated frames) tells the clients about it; no loop closure is announced for it.
PUBLISHED_EVENTS = TRACKING_EVENTS + INPUT_EVENTS + MAP_EVENTS

log = logging.getLogger(__name__)

# Both scripts fence on the lease: a worker that lost its session (paused past its lease) stores nothing more.
_STORE_RESULT = """
if redis.call('EXISTS', KEYS[1]) == 0 then return -1 end
if redis.call('GET', KEYS[5]) ~= ARGV[9] then return -2 end
local new = redis.call('HSETNX', KEYS[2], ARGV[1], ARGV[2])
if new == 1 then
  redis.call('HINCRBY', KEYS[1], 'frames_processed', 1)
  if ARGV[5] == '1' then redis.call('HINCRBY', KEYS[1], 'keyframes', 1) end
  redis.call('XADD', KEYS[3], 'MAXLEN', '~', ARGV[8], '*', 'msg', ARGV[3])
end
redis.call('HSET', KEYS[1], 'revision', ARGV[6], 'updated_at', ARGV[7])
redis.call('XACK', KEYS[4], 'workers', ARGV[4])
return new
"""
# A refused or skipped frame: its code in the rejected hash, the counter ARGV[7] incremented, the message out.
_STORE_REJECTION = """
if redis.call('EXISTS', KEYS[1]) == 0 then return -1 end
if redis.call('GET', KEYS[5]) ~= ARGV[6] then return -2 end
local new = redis.call('HSETNX', KEYS[2], ARGV[1], ARGV[2])
if new == 1 then
  redis.call('HINCRBY', KEYS[1], ARGV[7], 1)
  redis.call('XADD', KEYS[3], 'MAXLEN', '~', ARGV[5], '*', 'msg', ARGV[3])
end
redis.call('XACK', KEYS[4], 'workers', ARGV[4])
return new
"""

class SessionGone(Exception):
    """The session was deleted while we owned it."""


class LeaseLost(Exception):
    """Another worker owns the session now."""


def now_iso() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def stream_id_tuple(stream_id: bytes | str) -> tuple[int, int]:
    text = stream_id.decode() if isinstance(stream_id, bytes) else stream_id
    ms, _, seq = text.partition("-")
    return int(ms), int(seq or 0)


def ensure_group(client: redis.Redis, stream: str) -> None:
    """Create the "workers" consumer group on `stream` (and the stream) if missing."""
    try:
        client.xgroup_create(stream, keys.GROUP, id="0", mkstream=True)
    except redis.ResponseError as err:
        if "BUSYGROUP" not in str(err):
            raise


def _newest_frame_id(entries: list[tuple[bytes, dict[bytes, bytes]]]) -> bytes | None:
    """The id of the newest frame entry among `entries` (None when there is none)."""
    for entry_id, fields in reversed(entries):
        if fields.get(b"kind", b"frame") == b"frame":
            return entry_id
    return None


def tracking_state(event: ServerMessage) -> str:
    """The session's tracking state after a pose-source event."""
    if isinstance(event, TrackingLost):
        return "lost"
    return "initializing" if isinstance(event, (Initializing, NewMap)) else "tracking"


def pose_message(seq: int, timestamp: float, pose: np.ndarray, is_keyframe: bool, revision: int) -> bytes:
    return PoseMessage(seq=seq, timestamp=timestamp, pose=np.asarray(pose, dtype=np.float64).reshape(-1).tolist(),
                       scale=similarity_scale(pose), is_keyframe=bool(is_keyframe),
                       revision=int(revision)).to_json().encode()


class SessionRunner(threading.Thread):
    """Runs one session on this worker until it finishes, fails, is deleted, loses its lease or is stopped."""

    def __init__(self, client: redis.Redis, worker_id: str, session_id: str, job_id: str, leases: Leases,
                 config: RuntimeConfig, stats: StageStats) -> None:
        super().__init__(name=f"session-{session_id}", daemon=True)
        self.client = client
        self.worker_id = worker_id
        self.session_id = session_id
        self.job_id = job_id
        self.leases = leases
        self.config = config
        self.stats = stats
        self.engine: SessionEngine | None = None
        self.terminal = False  # finished, failed or deleted: the job is done
        self.interrupted = False  # Redis became unreachable: the worker takes the session again when it is back
        self._stop_event = threading.Event()
        self._lease_lost = threading.Event()
        self._done_seqs: set[int] = set()
        self._rejected: set[int] = set()
        self._cursor = (0, 0)
        self._keyframes_since_snapshot = 0
        self._map_exchange: MapExchange | None = None
        self._revision = 0
        self._last_id: bytes = b"0-0"
        self._session: dict[str, Any] = {}
        self._store_result = client.register_script(_STORE_RESULT)
        self._store_rejection = client.register_script(_STORE_REJECTION)
        self._snapshots = SnapshotWriter(client, session_id, worker_id)
        self._attempts = FrameAttempts(client, session_id, config.max_frame_attempts)
        self._record = SessionRecord(client, session_id)
        self._snapshot_in_flight: tuple[Any, int, bytes] | None = None  # (future, seq, entry id)
        self._snapshot_begun_at = time.monotonic()
        self._consecutive_skips = 0
        self._last_tracked_arrival_ms: float | None = None  # gateway arrival of the last frame not skipped
        self._tracking_state: str | None = None
        self._live_stats_at = 0.0
        self.claimed_at: float | None = None  # wall time the worker claimed a silent worker's job (takeovers)
        self._timeline: dict[str, Any] | None = None  # until the first pose: the phases of taking the session

    # --- control from the worker --------------------------------------------------------------------------------
    def stop(self) -> None:
        """Stop after the current frame (worker shutdown); the lease is released for another worker."""
        self._stop_event.set()

    def lease_lost(self) -> None:
        self._lease_lost.set()

    # --- thread body --------------------------------------------------------------------------------------------
    def run(self) -> None:
        self._timeline = {"worker": self.worker_id, "claimed_at": self.claimed_at, "started_at": time.time()}
        try:
            self._load_session()
            self._restore_and_replay()
            self._process_until_done()
        except SessionGone:
            self._clean_up_deleted()
        except LeaseLost:
            log.warning("session %s: lease lost, stopping", self.session_id)
        except REDIS_DOWN as err:
            # not the session's fault: it resumes from its snapshot (the inbox replays the rest) once Redis is back
            log.warning("session %s: Redis unreachable (%s); pausing it", self.session_id, err)
            self.interrupted = True
        except Exception as err:
            if self._deleted():  # e.g. NOGROUP: the delete removed the streams under a running step
                self._clean_up_deleted()
            else:
                log.exception("session %s failed", self.session_id)
                self._fail(err)
        finally:
            close_engine(self.engine)
            if not self._lease_lost.is_set() and not self.interrupted:
                try:
                    self.leases.release(self.session_id)
                except REDIS_DOWN:
                    pass  # the lease expires on its own

    def _deleted(self) -> bool:
        try:
            return not self.client.exists(keys.session(self.session_id))
        except redis.RedisError:
            return False

    def _clean_up_deleted(self) -> None:
        """The session was deleted while we ran it: remove what we created since (streams, lease)."""
        log.info("session %s was deleted", self.session_id)
        self.terminal = True
        failpoint("delete:worker")
        self.client.delete(*keys.all_session_keys(self.session_id))

    def _load_session(self) -> None:
        raw = self.client.hgetall(keys.session(self.session_id))
        if not raw:
            raise SessionGone
        self._session = {k.decode(): v.decode() for k, v in raw.items() if k != b"owner"}
        self._revision = int(self._session.get("revision", 0))
        if not self._record.update({"worker": self.worker_id, "updated_at": now_iso()}):
            raise SessionGone

    def _tracking_side(self) -> int | None:
        """The tracking resolution's long side: the session's, else the worker's default (None: as frames come)."""
        return int(self._session.get("tracking_side") or 0) or self.config.tracking_side or None

    def _decides_at_first_frame(self) -> bool:
        """Whether the engine waits for the session's first frame: its settings follow from the input (no preset
        named, none recorded yet)."""
        return (self.config.engine == "slam" and named_preset(self._session) is None
                and not self._session.get("settings"))

    def _create_engine(self, first_frame: Frame | None) -> None:
        """The session's engine, with the settings named, recorded or decided now from `first_frame` (None: before
        any frame, e.g. a session finished without one); a decision is written to the record once."""
        preset, overrides = self._session.get("preset") or None, None
        if self.config.engine == "slam":
            choice = session_settings(self._session, first_frame, this_machine(self.config.checkpoint))
            preset, overrides = choice.preset, choice.engine_overrides()
            if not self._session.get("settings"):
                text = json.dumps(choice.to_record())
                if not self._record.update({"settings": text}):
                    raise SessionGone
                self._session["settings"] = text
                log.info("session %s: settings %s (%s)", self.session_id, choice.preset, "; ".join(choice.reasons))
        self.engine = create_engine(self.config.engine, preset, session_camera(self._session_intrinsics()),
                                    pose_mode=self._session.get("pose_mode") or None,
                                    tracking_side=self._tracking_side(),
                                    depth_camera=json.loads(self._session.get("depth_camera") or "null"),
                                    overrides=overrides, in_map=self._in_map())

    def _in_map(self, restoring: bool = False) -> Any:
        """The stored map the session runs in (a worker.maps.SessionInMap), for a SLAM engine."""
        if self.config.engine != "slam":
            return None
        return session_in_map(self.client, self._session, restoring)

    def _decode(self, message: dict[str, Any]) -> Frame:
        """The frame at the session's working size; the session's first frame decides its settings (and the
        engine), which may name a smaller working size: that frame is then decoded again at it."""
        depth_in_colour = json.loads(self._session.get("depth_camera") or "null") is None
        frame = decode_frame(message, self._session_intrinsics(), self._max_frame_side(), depth_in_colour)
        if self.engine is None:
            self._create_engine(frame)
            if max(frame.image.shape[:2]) > self._max_frame_side():
                frame = decode_frame(message, self._session_intrinsics(), self._max_frame_side(), depth_in_colour)
        return frame

    def _max_frame_side(self) -> int:
        """The long side frames are worked on at: the worker's limit, or the settings' smaller working side."""
        working = json.loads(self._session.get("settings") or "{}").get("working_side")
        return min(self.config.max_frame_side, int(working)) if working else self.config.max_frame_side

    def _session_intrinsics(self) -> dict[str, Any] | None:
        text = self._session.get("intrinsics")
        return json.loads(text) if text and text != "null" else None

    def _restore_and_replay(self) -> None:
        ensure_group(self.client, keys.inbox(self.session_id))
        ensure_group(self.client, keys.session_requests(self.session_id))
        snap = read_snapshot(self.client, self.session_id)
        if snap is not None:
            self.engine = restore_engine(snap.engine, snap.data, snap.chunks, in_map=self._in_map(restoring=True))
            self._snapshots.restored(snap)
            self._last_id = snap.stream_id
            log.info("session %s restored from snapshot at seq %s", self.session_id, snap.seq)
            self._timeline.update(restored_at=time.time(), snapshot_seq=snap.seq, replayed=0)
        elif not self._decides_at_first_frame():
            self._create_engine(None)
        self._done_seqs = {int(s) for s in self.client.hkeys(keys.poses(self.session_id))}
        self._rejected = {int(s) for s in self.client.hkeys(keys.rejected(self.session_id))}
        self._done_seqs |= self._rejected
        # take over entries a dead owner left pending, then replay everything after the snapshot
        start = "0-0"
        while True:
            start, _claimed, *_ = self.client.xautoclaim(keys.inbox(self.session_id), keys.GROUP, self.worker_id,
                                                         min_idle_time=0, start_id=start, count=100)
            if start in (b"0-0", "0-0"):
                break
        after = self._last_id
        while not self.terminal:
            entries = self.client.xrange(keys.inbox(self.session_id), min=f"({after.decode()}", count=64)
            if not entries:
                break
            newest_frame = _newest_frame_id(entries)
            for entry_id, fields in entries:
                if self._should_skip(entry_id, fields, newest_frame):  # caught up live: old frames are skipped
                    self._skip(entry_id, int(fields[b"seq"]))
                else:
                    self._handle_entry(entry_id, fields)
                after = entry_id
                self._store_finished_snapshot()
            self._publish_live_stats()  # a stream that keeps coming is caught up on here
        self._cursor = stream_id_tuple(after)
        if self._timeline is not None:
            self._timeline.setdefault("replay_done_at", time.time())
        self._resume_interrupted_finish()

    def _process_until_done(self) -> None:
        streams = {keys.inbox(self.session_id): ">", keys.session_requests(self.session_id): ">"}
        idle_since = time.monotonic()
        while not self.terminal:
            if self._stop_event.is_set():
                return
            if self._lease_lost.is_set():
                raise LeaseLost
            t0 = time.perf_counter()
            try:
                reply = self.client.xreadgroup(keys.GROUP, self.worker_id, streams, count=16,
                                               block=self.config.block_ms)
            except redis.ResponseError as err:
                if "NOGROUP" in str(err) and not self.client.exists(keys.session(self.session_id)):
                    raise SessionGone from err
                raise
            if not reply:
                if not self.client.exists(keys.session(self.session_id)):
                    raise SessionGone
                timeout = self.config.idle_timeout_s
                if timeout and time.monotonic() - idle_since > timeout and not self._abandon(timeout):
                    idle_since = time.monotonic()  # a frame got in meanwhile: not idle after all
                continue
            idle_since = time.monotonic()
            frames = sum(len(e) for s, e in reply if s.decode() == keys.inbox(self.session_id))
            if frames:
                self.stats.add("read", time.perf_counter() - t0, frames)
            for stream, entries in self._requests_first_before_a_finish(reply):
                is_inbox = stream.decode() == keys.inbox(self.session_id)
                newest_frame = _newest_frame_id(entries) if is_inbox else None
                for entry_id, fields in entries:
                    if not is_inbox:
                        self._handle_request(entry_id, fields)
                    elif stream_id_tuple(entry_id) <= self._cursor:
                        self.client.xack(keys.inbox(self.session_id), keys.GROUP, entry_id)  # replayed already
                    elif self._should_skip(entry_id, fields, newest_frame):
                        self._skip(entry_id, int(fields[b"seq"]))
                        self._cursor = stream_id_tuple(entry_id)
                    else:
                        self._handle_entry(entry_id, fields)
                        self._cursor = stream_id_tuple(entry_id)
                    self._store_finished_snapshot()
            self._publish_live_stats()
        self._drain_requests()

    def _requests_first_before_a_finish(self, reply: list) -> list:
        """The streams of one read in the order to handle them: the inbox first (frames before renders), except
        when it ends the session: requests read with the finish are answered before it, not after the final
        refinement."""
        inbox = keys.inbox(self.session_id)
        finishing = any(fields.get(b"kind") == b"finish" for stream, entries in reply if stream.decode() == inbox
                        for _, fields in entries)
        return sorted(reply, key=lambda item: item[0].decode() == inbox) if finishing else list(reply)

    # --- live tracking ------------------------------------------------------------------------------------------
    def _should_skip(self, entry_id: bytes, fields: dict[bytes, bytes], newest_frame: bytes | None) -> bool:
        """Newest first wins: a frame that waited longer than `skip_after_ms` while a newer frame is waiting is
        skipped (never the session's first frame, a frame already counted, more than a few in a row, a second one
        in a row that arrived more than `max_skipped_span_ms` after the last tracked frame, or while the engine
        keeps every frame: judging device poses over the first frames, worker.tracking.pose_choice; registering
        photos, worker.tracking.photos)."""
        if fields.get(b"kind", b"frame") != b"frame":
            return False
        limit = self.config.skip_after_ms if self._session.get("skip_frames") == "1" else 0
        if getattr(self.engine, "keeps_every_frame", False):
            limit = 0
        arrival_ms = float(stream_id_tuple(entry_id)[0])
        span_ms = 0.0 if self._last_tracked_arrival_ms is None else arrival_ms - self._last_tracked_arrival_ms
        if (limit <= 0 or newest_frame is None or entry_id == newest_frame or not self._done_seqs
                or self._consecutive_skips >= self.config.max_consecutive_skips
                or (self._consecutive_skips > 0 and span_ms > self.config.max_skipped_span_ms)
                or int(fields[b"seq"]) in self._done_seqs
                or time.time() * 1000.0 - arrival_ms <= limit):
            self._consecutive_skips = 0
            self._last_tracked_arrival_ms = arrival_ms
            return False
        self._consecutive_skips += 1
        return True

    def _skip(self, entry_id: bytes, seq: int) -> None:
        """Answer a skipped frame with a `skipped` message (its seq is done: no pose will come for it)."""
        out = SkippedMessage(seq=seq, reason="overload").to_json().encode()
        status = self._store_rejection(
            keys=[keys.session(self.session_id), keys.rejected(self.session_id), keys.outbox(self.session_id),
                  keys.inbox(self.session_id), keys.lease(self.session_id)],
            args=[seq, "skipped", out, entry_id, self.config.outbox_maxlen, self.worker_id, "frames_skipped"])
        self._check_store_status(status)
        self._done_seqs.add(seq)
        self._rejected.add(seq)

    def _publish_live_stats(self, force: bool = False) -> None:
        """The engine's live figures (mapping lag, tracking state) into the session record, at most every
        `live_stats_every_s`."""
        now = time.monotonic()
        if not force and now - self._live_stats_at < self.config.live_stats_every_s:
            return
        self._live_stats_at = now
        live_stats = getattr(self.engine, "live_stats", None)
        fields: dict[str, Any] = {}
        if live_stats is not None:
            figures = live_stats()
            fields = {"mapping_lag_keyframes": int(figures["mapping_lag_keyframes"]),
                      "mapping_lag_s": round(float(figures["mapping_lag_s"]), 3)}
        if self._tracking_state is not None:
            fields["tracking_state"] = self._tracking_state
            in_map = getattr(self.engine, "in_map", None)
            if in_map is not None and not in_map.anchored and self._tracking_state == "tracking":
                fields["tracking_state"] = "not_relocalized"  # tracking, in its own world until it is
        if fields and not self._record.update(fields):
            raise SessionGone

    # --- entries ------------------------------------------------------------------------------------------------
    def _handle_entry(self, entry_id: bytes, fields: dict[bytes, bytes]) -> None:
        kind = fields.get(b"kind", b"frame")
        if kind == b"finish":
            self._finish(entry_id)
            return
        seq = int(fields[b"seq"])
        if seq in self._done_seqs:
            self._replay_frame(fields)
            self.client.xack(keys.inbox(self.session_id), keys.GROUP, entry_id)
            return
        self._process_frame(entry_id, seq, fields)

    def _replay_frame(self, fields: dict[bytes, bytes]) -> None:
        """Feed an already-counted frame to a restored engine so its state catches up (no results emitted)."""
        if int(fields[b"seq"]) not in self._rejected:
            if self._timeline is not None:
                self._timeline["replayed"] = self._timeline.get("replayed", 0) + 1
            try:
                self.engine.push(self._decode(unpack(fields[b"msg"])))
            except (FrameError, ValueError) as err:
                log.warning("replay of seq %s failed: %s", fields[b"seq"], err)

    def _process_frame(self, entry_id: bytes, seq: int, fields: dict[bytes, bytes]) -> None:
        if self._timeline is not None:
            self._timeline.setdefault("replay_done_at", time.time())
        if not self._attempts.begin(seq):  # before anything that could take the worker down with this frame
            raise SessionGone
        t0, c0 = time.perf_counter(), time.thread_time()
        try:
            frame = self._decode(unpack(fields[b"msg"]))
        except FrameError as err:
            self._reject(entry_id, seq, err.code, str(err))
            return
        except (ValueError, KeyError, TypeError) as err:
            self._reject(entry_id, seq, "bad_frame", f"frame cannot be used: {err}")
            return
        t1, c1 = time.perf_counter(), time.thread_time()
        try:
            result = self.engine.push(frame)
        except ValueError as err:  # the engine refuses this frame (e.g. a size it cannot take); the session goes on
            self._reject(entry_id, seq, "bad_frame", f"engine refused the frame: {err}")
            return
        t2, c2 = time.perf_counter(), time.thread_time()
        record = pack({"t": result.timestamp, "p": np.asarray(result.pose, dtype=np.float64).reshape(-1).tolist(),
                       "kf": bool(result.is_keyframe)})
        out = pose_message(seq, result.timestamp, result.pose, result.is_keyframe, result.revision)
        status = self._store_result(
            keys=[keys.session(self.session_id), keys.poses(self.session_id), keys.outbox(self.session_id),
                  keys.inbox(self.session_id), keys.lease(self.session_id)],
            args=[seq, record, out, entry_id, int(result.is_keyframe), result.revision, now_iso(),
                  self.config.outbox_maxlen, self.worker_id])
        self._check_store_status(status)
        self._done_seqs.add(seq)
        if self._timeline is not None:
            self._publish_timeline(seq)
        t3, c3 = time.perf_counter(), time.thread_time()
        self.stats.add("decode", t1 - t0)
        self.stats.add("engine", t2 - t1)
        self.stats.add("store", t3 - t2)
        self.stats.add("dispatch", (t1 - t0) + (t3 - t2))
        # CPU time of this thread alone: the overhead itself, without the waits for a core or the GIL under load
        self.stats.add("dispatch_cpu", (c1 - c0) + (c3 - c2))
        if result.revision != self._revision or any(isinstance(e, LoopClosed) for e in result.events):
            self._publish_revision(result.revision, result.events)
        for event in result.events:
            if isinstance(event, TRACKING_EVENTS):
                self._publish_event(seq, event)
                self._tracking_state = tracking_state(event)
            elif isinstance(event, INPUT_EVENTS + MAP_EVENTS):
                self._publish_event(seq, event)
                if isinstance(event, DepthMisregistered):
                    self._add_warning(event.message or "depth is not registered to the colour image")
                if isinstance(event, PoseSourceChosen) and event.pose_source == "seeded":
                    self._add_warning(event.reason or "device poses disagree with the images")
        self._tracking_state = self._tracking_state or "tracking"
        if not self._session.get("estimated_intrinsics") or any(
                isinstance(e, engine_events.Initialized) and e.intrinsics for e in result.events):  # (re-)estimated
            self._publish_estimated_intrinsics()
        self._exchange_places(result.is_keyframe)
        if result.is_keyframe:
            self._keyframes_since_snapshot += 1
        every_s = self.config.snapshot_every_s
        if (self._keyframes_since_snapshot >= self.config.snapshot_every
                or (every_s > 0 and time.monotonic() - self._snapshot_begun_at >= every_s)):
            self._write_snapshot(seq, entry_id)

    def _exchange_places(self, keyframe: bool) -> None:
        """A session in a map: its new places out to the map's live stream, the other sessions' in
        (worker.runtime.map_exchange)."""
        in_map = getattr(self.engine, "in_map", None)
        if in_map is None:
            return
        if self._map_exchange is None or self._map_exchange.in_map is not in_map:
            self._map_exchange = MapExchange(self.client, self.session_id, in_map)
        self._map_exchange.exchange(keyframe)

    def _publish_timeline(self, seq: int) -> None:
        """The first pose since this worker took the session: its phases (wall times: claimed, started, restored,
        replayed, first pose) go to the record's `takeover` field, for the kill benchmarks."""
        timeline, self._timeline = self._timeline, None
        timeline.update(first_pose_at=time.time(), first_pose_seq=seq)
        if not self._record.update({"takeover": json.dumps(timeline)}):
            raise SessionGone

    def _add_warning(self, text: str) -> None:
        """Keep a notice about the input in the session record (`warnings`), once."""
        warnings = json.loads(self._session.get("warnings") or "[]")
        if text in warnings:
            return
        value = json.dumps(warnings + [text])
        if not self._record.update({"warnings": value}):
            raise SessionGone
        self._session["warnings"] = value

    def _publish_estimated_intrinsics(self) -> None:
        """Once the engine knows the camera (given, or estimated from monocular frames), put it in the session
        record so clients can render views that match their camera."""
        camera = engine_intrinsics(self.engine)
        if camera is not None:
            text = json.dumps(camera)
            if not self._record.update({"estimated_intrinsics": text}):
                raise SessionGone
            self._session["estimated_intrinsics"] = text

    def _abandon(self, idle_s: float) -> bool:
        """No frame for `idle_s`: snapshot what was processed, mark the session `abandoned` and free this slot.
        A stream opened within the gateway's grace period resumes it (from this snapshot) on any worker."""
        if self._done_seqs and self._cursor != stream_id_tuple(self._last_id):
            self._write_snapshot(max(self._done_seqs), f"{self._cursor[0]}-{self._cursor[1]}".encode(), wait=True)
        message = ErrorMessage(code="abandoned",
                               message=f"no frame for {idle_s:g} s: the session was abandoned; open a stream "
                                       "again within the grace period to resume it").to_json().encode()
        if not self._record.abandon(message, self.config.outbox_maxlen, time.time(), now_iso()):
            return False
        log.info("session %s abandoned after %g s without frames", self.session_id, idle_s)
        self.terminal = True
        return True

    def _reject(self, entry_id: bytes, seq: int, code: ErrorCode, message: str) -> None:
        out = ErrorMessage(code=code, message=message, seq=seq).to_json().encode()
        status = self._store_rejection(
            keys=[keys.session(self.session_id), keys.rejected(self.session_id), keys.outbox(self.session_id),
                  keys.inbox(self.session_id), keys.lease(self.session_id)],
            args=[seq, code, out, entry_id, self.config.outbox_maxlen, self.worker_id, "frames_rejected"])
        self._check_store_status(status)
        self._done_seqs.add(seq)
        self._rejected.add(seq)

    def _check_store_status(self, status: int) -> None:
        if status == -1:
            raise SessionGone
        if status == -2:
            self._lease_lost.set()
            raise LeaseLost

    def _publish_event(self, seq: int, event: engine_events.EngineEvent) -> None:
        """Tell the clients what the engine found at frame `seq`: tracking lost, back or initialised (never a silent
        jump), a notice about the input, a map's correction."""
        self._publish(event.to_message(seq=seq))

    def _publish(self, message: ServerMessage) -> None:
        self.client.xadd(keys.outbox(self.session_id), {"msg": message.to_json().encode()},
                         maxlen=self.config.outbox_maxlen, approximate=True)

    def _publish_revision(self, revision: int, events: list[engine_events.EngineEvent]) -> None:
        """A loop closure (or a pose source's re-estimate of past frames) rewrote the past: store the whole new
        trajectory and tell the clients (an event sent as its own message that rewrote it, such as `initialized`
        or `pose_source_chosen`, carries the revision itself: no `loop_closed` is made up for it)."""
        self._revision = revision
        self._store_trajectory()
        loops = [e for e in events if isinstance(e, LoopClosed)]
        if not loops and not any(isinstance(e, PUBLISHED_EVENTS) and getattr(e, "revision", None) is not None
                                 for e in events):
            loops = [engine_events.LoopClosed()]
        for event in loops:
            self._publish(event.to_message(revision=revision))

    def _store_trajectory(self) -> None:
        keyframes = {int(i) for i, _, _ in self.engine.trajectory("keyframes")}
        mapping = {int(i): pack({"t": float(t), "p": np.asarray(p, dtype=np.float64).reshape(-1).tolist(),
                                 "kf": int(i) in keyframes})
                   for i, t, p in self.engine.trajectory("all")}
        fields = {"revision": self._revision, "keyframes": len(keyframes), "updated_at": now_iso()}
        if mapping and not self._record.store_trajectory(mapping, fields):
            raise SessionGone

    def _write_snapshot(self, seq: int, entry_id: bytes, wait: bool = False) -> None:
        """Snapshot the engine as of frame `seq` (inbox entry `entry_id`). An engine that can take it without
        stopping (`begin_snapshot`) delivers it later and `_store_finished_snapshot` stores it then; one snapshot
        at a time is in flight (a later one is asked for at the next keyframe). `wait` stores it now."""
        begin = getattr(self.engine, "begin_snapshot", None)
        if begin is None or wait:  # self-contained: a finished session's snapshot is read without its chunks
            self._snapshot_in_flight = None  # superseded by this one
            self._store_snapshot_blob(self.engine.snapshot(), None, seq, entry_id)
            self._keyframes_since_snapshot = 0
            return
        if self._snapshot_in_flight is not None:
            return
        self._snapshot_in_flight = (begin(stored_chunks=dict(self._snapshots.stored_chunks)), seq, entry_id)
        self._snapshot_begun_at = time.monotonic()
        self._keyframes_since_snapshot = 0

    def _store_finished_snapshot(self) -> None:
        """Store the snapshot in flight once the engine's stages have delivered it."""
        if self._snapshot_in_flight is None or not self._snapshot_in_flight[0].done():
            return
        future, seq, entry_id = self._snapshot_in_flight
        self._snapshot_in_flight = None
        self._store_snapshot_blob(future.result(), getattr(future, "chunks", None), seq, entry_id)

    def _store_snapshot_blob(self, blob: bytes, chunks: ChunkWrite | None, seq: int, entry_id: bytes) -> None:
        t0 = time.perf_counter()
        status = self._snapshots.write(blob, chunks, seq, entry_id, self.config.engine, now_iso())
        self._check_store_status(status)
        self._last_id = entry_id
        self.stats.add("snapshot", time.perf_counter() - t0)

    def _finish(self, entry_id: bytes) -> None:
        if self.engine is None:  # finished before any frame
            self._create_engine(None)
        finish_status = getattr(self.engine, "finish_status", None)
        with (FinishProgress(self.client, self.session_id, outbox_maxlen=self.config.outbox_maxlen,
                             status=finish_status.as_dict if finish_status is not None else None),
              RequestsWhileFinishing(self.client, self.session_id, self.worker_id, self._handle_request)):
            self.engine.finish()
        if not self.leases.renew(self.session_id):
            self._lease_lost.set()
            raise LeaseLost
        failpoint("finish:engine")
        revision = int(getattr(self.engine, "revision", self._revision))
        last_seq = max(self._done_seqs) if self._done_seqs else -1
        # loops closed while finishing, the final refinement's camera corrections: told like the others
        finish_events = list(getattr(self.engine, "finish_events", []))
        extended = extend_stored_map(self.client, self.engine, self.session_id)  # an `extend` session's map
        if extended is not None:
            self._publish_event(last_seq, extended)
        if finish_events:
            self._publish_revision(revision, finish_events)
            for event in finish_events:  # a relocalization in a stored map may come this late too
                if isinstance(event, PUBLISHED_EVENTS):
                    self._publish_event(last_seq, event)
        else:
            self._revision = revision
            self._store_trajectory()
        self._publish_live_stats(force=True)  # drained: the lag reads 0 from now on
        failpoint("finish:trajectory")
        self._write_snapshot(last_seq, entry_id, wait=True)
        failpoint("finish:snapshot")
        self._mark_finished(entry_id)

    def _mark_finished(self, entry_id: bytes) -> None:
        """The last step of finishing, after the final snapshot: status, the `finished` message, the ack."""
        frames = int(self.client.hget(keys.session(self.session_id), "frames_processed") or 0)
        message = FinishedMessage(frames=frames).to_json().encode()
        if not self._record.close({"status": "finished", "updated_at": now_iso()}, message,
                                  self.config.outbox_maxlen, entry_id, self.config.transient_ttl_s,
                                  self.config.retention_s):
            raise SessionGone
        failpoint("finish:marked")
        self.terminal = True

    def _resume_interrupted_finish(self) -> None:
        """A worker died after the final snapshot but before marking the session finished: the restored engine is
        the finished one and its snapshot sits at the finish entry, so only the marking is left to do."""
        if self.terminal or self._session.get("status") != "finishing":
            return
        entries = self.client.xrange(keys.inbox(self.session_id), min=self._last_id, max=self._last_id)
        if entries and entries[0][1].get(b"kind") == b"finish":
            log.info("session %s: completing a finish its previous worker did not", self.session_id)
            self._revision = int(getattr(self.engine, "revision", self._revision))
            self._store_trajectory()
            self._mark_finished(entries[0][0])

    def _fail(self, err: Exception) -> None:
        self.terminal = True
        try:
            message = ErrorMessage(code="engine_failed", message=f"session failed: {err}").to_json()
            self._record.close({"status": "failed", "error": str(err)[:500], "updated_at": now_iso()},
                               message.encode(), self.config.outbox_maxlen, None, self.config.transient_ttl_s,
                               self.config.retention_s)
        except redis.RedisError:
            log.exception("could not record the failure of session %s", self.session_id)

    # --- requests -----------------------------------------------------------------------------------------------
    def _handle_request(self, entry_id: bytes, fields: dict[bytes, bytes]) -> None:
        t0 = time.perf_counter()
        handle_request(self.client, self.engine, fields)
        self.client.xack(keys.session_requests(self.session_id), keys.GROUP, entry_id)
        self.stats.add("render", time.perf_counter() - t0)

    def _drain_requests(self) -> None:
        """Answer requests that arrived while the session was finishing."""
        reply = self.client.xreadgroup(keys.GROUP, self.worker_id, {keys.session_requests(self.session_id): ">"},
                                       count=100)
        for _stream, entries in reply or []:
            for entry_id, fields in entries:
                self._handle_request(entry_id, fields)
