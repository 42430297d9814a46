"""An independent WebSocket client of the stream protocol, written from openapi.yaml's x-websocket text alone
(websockets + msgpack, no SDK code): it pipelines frames at a fixed rate and recovers from backpressure by the
documented rule. Used by tests/client/test_pipelined_streaming.py and bench/pipelined.py."""

from __future__ import annotations

import collections
import json
import threading
import time

from websockets.sync.client import connect


class RawPipelinedClient:
    """A client built from the protocol description alone: frames go out at `fps` without waiting for acks; the
    server answers frames in the order they arrived; on `backpressure` the sender rewinds to `resend_from`.
    Answers to frames sent before the latest rewind are stale and ignored (`epoch`)."""

    def __init__(self, url: str, messages: list[bytes], fps: float) -> None:
        self.url, self.messages, self.fps = url, messages, fps
        self.lock = threading.Lock()
        self.next_seq, self.epoch, self.resume_at = 0, 0, 0.0
        self.unanswered: collections.deque[tuple[int, int]] = collections.deque()  # (seq, epoch) in send order
        self.acked: list[int] = []
        self.rewinds = 0
        self.poses: list[dict] = []
        self.finished = threading.Event()
        self.failure: str | None = None

    def run(self, timeout_s: float = 120.0) -> None:
        with connect(self.url, open_timeout=30) as ws:
            reader = threading.Thread(target=self._read, args=(ws,), daemon=True)
            reader.start()
            start = time.monotonic()
            deadline = start + timeout_s
            while time.monotonic() < deadline and self.failure is None:
                with self.lock:
                    if self.next_seq >= len(self.messages):
                        if len(self.acked) == len(self.messages):
                            break
                        wait_until = time.monotonic() + 0.01
                    else:
                        seq = self.next_seq
                        wait_until = max(start + seq / self.fps, self.resume_at)
                if time.monotonic() < wait_until:
                    time.sleep(wait_until - time.monotonic())
                    continue
                with self.lock:
                    if seq != self.next_seq:  # a rewind happened while sleeping
                        continue
                    self.unanswered.append((seq, self.epoch))
                    self.next_seq += 1
                ws.send(self.messages[seq])
            ws.send(json.dumps({"type": "finish"}))
            self.finished.wait(max(1.0, deadline - time.monotonic()))
        assert self.failure is None, self.failure
        assert self.finished.is_set(), f"no finished message; acked {len(self.acked)}"

    def _read(self, ws) -> None:
        for raw in ws:
            message = json.loads(raw)
            kind = message["type"]
            if kind in ("ack", "error") and "seq" in message:
                with self.lock:
                    seq, epoch = self.unanswered.popleft()
                    if seq != message["seq"]:
                        self.failure = f"answer for seq {message['seq']} while {seq} was the oldest unanswered"
                    elif kind == "ack":
                        self.acked.append(seq)
                    elif message["code"] != "backpressure":
                        self.failure = f"frame {seq} refused: {message}"
                    elif epoch == self.epoch:  # the first refusal since the last rewind
                        self.epoch += 1
                        self.rewinds += 1
                        self.next_seq = message["resend_from"]
                        self.resume_at = time.monotonic() + 0.05
            elif kind == "pose":
                self.poses.append(message)
            elif kind == "finished":
                self.finished.set()
                return
