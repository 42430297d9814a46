"""Moved to `protocol.codec` (the msgpack codec the gateway, the SDK and the workers share); the engine's modules
still import it from here."""

from protocol.codec import EXTERNAL_MIN_BYTES, pack, unpack  # noqa: F401
