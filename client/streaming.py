"""Client-side streaming: where frames come from, how they go on the wire, and how fast to send them.

- `open_frames(source)` gives an iterator of frames from a video file, an image folder, a dataset
  (anything `worker.data.open_source` reads, including ``synthetic://...``: these need the engine's readers, and
  torch), a webcam (``webcam:0`` or an int, a torch-free `StreamFrame` each) or an iterable of frames (any
  `FrameLike`: `StreamFrame`, `worker.data.frame.Frame`).
- `encode_frame_message(frame, seq)` is the binary msgpack message a phone sends: JPEG image, optional
  intrinsics, 16-bit PNG depth in millimetres and device pose.
- `FlowControl` keeps the client polite: a window of un-acknowledged frames, a bound on frames the server has
  queued but not processed yet (acked minus results), and ordered recovery when the server refuses a frame with
  a ``backpressure`` error.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from client.frames import FrameLike, StreamFrame, is_frame
from protocol.codec import pack

WEBCAM_PREFIX = "webcam:"
MAX_DEPTH_MM = 65535


# ----------------------------------------------------------------------------------------------- frame sources


class WebcamSource:
    """Frames from a camera opened with `cv2.VideoCapture(index)`, timestamped with the local clock."""

    def __init__(self, index: int, max_frames: int | None = None, resize: tuple[int, int] | None = None) -> None:
        self.index = index
        self.max_frames = max_frames
        self.resize = resize
        self.name = f"webcam{index}"

    def __iter__(self) -> Iterator[StreamFrame]:
        capture = cv2.VideoCapture(self.index)
        if not capture.isOpened():
            capture.release()
            raise ValueError(f"could not open webcam {self.index} (is a camera attached and accessible?)")
        start = time.monotonic()
        count = 0
        try:
            while self.max_frames is None or count < self.max_frames:
                ok, bgr = capture.read()
                if not ok:
                    break
                if self.resize is not None:
                    bgr = cv2.resize(bgr, self.resize, interpolation=cv2.INTER_AREA)
                rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
                yield StreamFrame(index=count, timestamp=time.monotonic() - start, image=rgb)
                count += 1
        finally:
            capture.release()


def _webcam_index(source: Any) -> int | None:
    if isinstance(source, int) and not isinstance(source, bool):
        return source
    if isinstance(source, str) and source.startswith(WEBCAM_PREFIX):
        suffix = source[len(WEBCAM_PREFIX):]
        if not suffix.isdigit():
            raise ValueError(f"a webcam source looks like 'webcam:0', got {source!r}")
        return int(suffix)
    return None


def open_frames(source: Any, *, stride: int = 1, max_frames: int | None = None,
                resize: tuple[int, int] | None = None, **options: Any) -> Iterable[FrameLike]:
    """Frames from `source`: a path/URI for `worker.data.open_source`, a webcam, or an iterable of Frames.

    `stride`, `max_frames` and `resize` (width, height) apply to every kind of source; other options go to
    `open_source` (e.g. use_gt_depth / use_gt_poses for datasets).
    """
    if stride < 1:
        raise ValueError("stride must be >= 1")
    if max_frames is not None and max_frames < 1:
        raise ValueError("max_frames must be >= 1")
    index = _webcam_index(source)
    if index is not None:
        if stride != 1:
            raise ValueError("stride does not apply to a webcam")
        return WebcamSource(index, max_frames=max_frames, resize=resize)
    if isinstance(source, (str, bytes)) or hasattr(source, "__fspath__"):
        from worker.data import open_source  # lazy: pulls in the dataset readers

        return open_source(str(source), stride=stride, max_frames=max_frames, resize=resize, **options)
    if isinstance(source, Iterable):
        return _limit(source, stride, max_frames)
    raise ValueError(f"cannot stream from {source!r}: give a path, a 'webcam:N' string or an iterable of Frames")


def _limit(frames: Iterable[FrameLike], stride: int, max_frames: int | None) -> Iterator[FrameLike]:
    sent = 0
    for i, frame in enumerate(frames):
        if i % stride:
            continue
        if max_frames is not None and sent >= max_frames:
            return
        if not is_frame(frame):
            raise ValueError(f"expected frames (StreamFrame, worker.data.frame.Frame), got {type(frame).__name__}")
        yield frame
        sent += 1


# ---------------------------------------------------------------------------------------------- wire encoding


def encode_jpeg(image_rgb: np.ndarray, quality: int = 90) -> bytes:
    """JPEG bytes of an RGB uint8 image."""
    if not 1 <= quality <= 100:
        raise ValueError("JPEG quality must be in 1..100")
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def encode_depth_png(depth_m: np.ndarray) -> bytes:
    """16-bit PNG of a metric depth map in millimetres (0 = invalid; beyond 65.535 m clipped)."""
    depth = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    mm = np.clip(np.round(depth * 1000.0), 0, MAX_DEPTH_MM).astype(np.uint16)
    ok, buf = cv2.imencode(".png", mm)
    if not ok:
        raise ValueError("depth PNG encoding failed")
    return buf.tobytes()


@dataclass(frozen=True)
class WireOptions:
    """What each frame message carries besides the JPEG image."""

    jpeg_quality: int = 90
    send_intrinsics: bool = True
    send_depth: bool = False
    send_pose: bool = False


def encode_frame_message(frame: FrameLike, seq: int, options: WireOptions = WireOptions()) -> bytes:
    """The binary msgpack message {type: "frame", seq, timestamp, image, intrinsics?, depth?, pose?}."""
    message: dict[str, Any] = {"type": "frame", "seq": int(seq), "timestamp": float(frame.timestamp),
                               "image": encode_jpeg(frame.image, options.jpeg_quality)}
    if options.send_intrinsics and frame.intrinsics is not None:
        k = frame.intrinsics
        message["intrinsics"] = {"fx": float(k.fx), "fy": float(k.fy), "cx": float(k.cx), "cy": float(k.cy)}
    if options.send_depth and frame.depth is not None:
        message["depth"] = encode_depth_png(frame.depth)
    if options.send_pose and frame.pose is not None:
        message["pose"] = [float(v) for v in np.asarray(frame.pose, dtype=np.float64).reshape(-1)]
    return pack(message)


# ----------------------------------------------------------------------------------------------- flow control


class FlowControl:
    """Decides when the next frame may go out, and what to re-send after the server refused frames.

    A frame is *in flight* from sending until its ack (or error). A frame is *pending* at the server from its
    ack until its result (pose or error). The client sends only while in_flight < window and
    in_flight + pending < max_pending. A ``backpressure`` refusal stops new frames until every in-flight frame has
    an answer; then the refused frames are re-sent in order after an exponential back-off, the first one alone
    until the server accepts it (a full window would mostly be refused again). The server refuses every
    frame after a refused one until that one is re-sent (``resend_from``), so nothing is lost; a refused frame
    older than an accepted one (a server without that rule) is dropped, since re-sending it would reorder the stream.
    `max_retries` bounds the re-send rounds in a row without any frame accepted.
    """

    def __init__(self, window: int = 4, max_pending: int = 8, max_retries: int = 20,
                 backoff_s: float = 0.05, max_backoff_s: float = 1.0) -> None:
        if window < 1 or max_pending < 1:
            raise ValueError("window and max_pending must be >= 1")
        if max_retries < 0:
            raise ValueError("max_retries must be >= 0")
        self.window = window
        self.max_pending = max_pending
        self.max_retries = max_retries
        self.backoff_s = backoff_s
        self.max_backoff_s = max_backoff_s
        self.items: dict[int, Any] = {}  # seq -> item, for every frame not yet settled
        self.in_flight: set[int] = set()  # sent, no ack yet
        self.pending: set[int] = set()  # acked, no result yet
        self.refused: set[int] = set()  # refused for backpressure, waiting for recovery
        self.accepted: set[int] = set()  # every seq the server queued
        self.server_queue_depth = 0
        self.refusal_rounds = 0  # re-send rounds since the last accepted frame
        self.probing = False  # after a refusal round: one frame at a time until the server accepts one
        self.retries = 0
        self.dropped: list[Any] = []
        self._result_before_ack: set[int] = set()

    # -- events from the wire
    def on_sent(self, seq: int, item: Any) -> None:
        self.items[seq] = item
        self.in_flight.add(seq)

    def on_ack(self, seq: int, queue_depth: int | None = None) -> None:
        if queue_depth is not None:
            self.server_queue_depth = int(queue_depth)
        if seq not in self.in_flight:  # a refusal already answered it, or a duplicate ack
            return
        self.in_flight.discard(seq)
        self.accepted.add(seq)
        self.refusal_rounds = 0
        self.probing = False
        if seq in self._result_before_ack:
            self._settle(seq)
        else:
            self.pending.add(seq)

    def on_result(self, seq: int) -> None:
        if seq in self.in_flight:  # the result overtook its ack
            self._result_before_ack.add(seq)
            return
        self.pending.discard(seq)
        self._settle(seq)

    def on_refused(self, seq: int) -> None:
        if seq not in self.items:
            return
        self.in_flight.discard(seq)
        self.pending.discard(seq)  # the ack came first: the refusal wins
        self.accepted.discard(seq)
        self.refused.add(seq)

    def on_rejected(self, seq: int) -> None:
        """A non-retryable error for this frame (corrupt image...): settled, never re-sent."""
        self.in_flight.discard(seq)
        self.pending.discard(seq)
        self._settle(seq)

    def _settle(self, seq: int) -> None:
        self.items.pop(seq, None)
        self._result_before_ack.discard(seq)

    # -- decisions
    def can_send(self) -> bool:
        if self.refused or (self.probing and self.in_flight):
            return False
        return len(self.in_flight) < self.window and len(self.in_flight) + len(self.pending) < self.max_pending

    def recovery_ready(self) -> bool:
        """True when frames were refused and every in-flight frame has its answer."""
        return bool(self.refused) and not self.in_flight

    def take_resends(self) -> tuple[list[tuple[int, Any]], float]:
        """((seq, item) pairs to re-send in order under the same seq, seconds to wait first); drops refused frames
        overtaken by accepted ones.

        Raises BackpressureError after more than max_retries rounds in a row without an accepted frame.
        """
        self.refusal_rounds += 1
        if self.refusal_rounds > self.max_retries:
            from client.errors import BackpressureError

            raise BackpressureError(
                f"the server refused frames {self.refusal_rounds} times in a row (queue full); giving up",
                code="backpressure")
        newest_accepted = max(self.accepted, default=-1)
        resend: list[tuple[int, Any]] = []
        for seq in sorted(self.refused):
            item = self.items.pop(seq)
            if seq < newest_accepted:
                self.dropped.append(item)
            else:
                resend.append((seq, item))
        self.refused.clear()
        self.probing = True
        self.retries += len(resend)
        delay = min(self.max_backoff_s, self.backoff_s * (2 ** (self.refusal_rounds - 1)))
        return resend, delay

    @property
    def unsettled(self) -> int:
        return len(self.in_flight) + len(self.pending) + len(self.refused)
