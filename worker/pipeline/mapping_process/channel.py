"""The byte channel between a session and its mapping process: msgpack messages (protocol.codec: dicts, numbers,
bytes and arrays) over one end of a multiprocessing pipe, sent and received as bytes (`send_bytes` / `recv_bytes`:
nothing is pickled). Any thread may send; one thread receives. With an outbox, `send` only queues the message and a
writer thread of the channel packs and writes it, in order: a sender never waits for the other process to read
(a pipe holds 64 KiB; a keyframe job is larger)."""

from __future__ import annotations

import queue
import threading
from multiprocessing.connection import Connection
from typing import Any

from protocol.codec import pack, unpack


class ChannelClosed(Exception):
    """The other end is gone (its process exited or was killed)."""


class Channel:
    """One end of the pipe, with a lock so that messages from several threads never interleave."""

    def __init__(self, conn: Connection, outbox: bool = False) -> None:
        self.conn = conn
        self._send_lock = threading.Lock()
        self._outbox: queue.SimpleQueue | None = None
        self._writer: threading.Thread | None = None
        if outbox:
            self._outbox = queue.SimpleQueue()
            self._writer = threading.Thread(target=self._write, name="mapping-channel-writer", daemon=True)
            self._writer.start()

    def send(self, message: dict[str, Any]) -> None:
        """Pack and send one message (ChannelClosed when the other end is gone); with an outbox, queue it (never
        blocks; a message queued when the other end is gone is dropped)."""
        if self._outbox is not None:
            self._outbox.put(message)
            return
        self.send_packed(pack(message))

    def _write(self) -> None:
        assert self._outbox is not None
        while (message := self._outbox.get()) is not None:
            try:
                self.send_packed(pack(message))
            except ChannelClosed:
                return  # the reader sees the other end gone

    def send_packed(self, data: bytes) -> None:
        """Send one message packed already (`pack`), e.g. kept to be sent again."""
        try:
            with self._send_lock:
                self.conn.send_bytes(data)
        except (BrokenPipeError, ConnectionResetError, EOFError, OSError) as err:
            raise ChannelClosed(str(err)) from err

    def receive(self) -> dict[str, Any]:
        """The next message (ChannelClosed when the other end is gone)."""
        try:
            data = self.conn.recv_bytes()
        except (EOFError, ConnectionResetError, OSError) as err:
            raise ChannelClosed(str(err)) from err
        message = unpack(data)
        if not isinstance(message, dict) or "op" not in message:
            raise ValueError("a mapping-process message must be a dict with an 'op'")
        return message

    def close(self, drain_s: float = 5.0) -> None:
        """Close the pipe, after writing what the outbox holds (for at most `drain_s` seconds)."""
        if self._outbox is not None and self._writer is not None:
            self._outbox.put(None)
            self._writer.join(drain_s)
        try:
            self.conn.close()
        except OSError:
            pass
