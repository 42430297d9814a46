"""The byte channel between a session and its mapping process: msgpack messages (protocol.codec: dicts, numbers,
bytes and arrays) over one end of a multiprocessing pipe, sent and received as bytes (`send_bytes` / `recv_bytes`:
nothing is pickled). Any thread may send; one thread receives."""

from __future__ import annotations

import threading
from multiprocessing.connection import Connection
from typing import Any

from protocol.codec import pack, unpack


class ChannelClosed(Exception):
    """The other end is gone (its process exited or was killed)."""


class Channel:
    """One end of the pipe, with a lock so that messages from several threads never interleave."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self._send_lock = threading.Lock()

    def send(self, message: dict[str, Any]) -> None:
        """Pack and send one message (ChannelClosed when the other end is gone)."""
        self.send_packed(pack(message))

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

    def close(self) -> None:
        try:
            self.conn.close()
        except OSError:
            pass
