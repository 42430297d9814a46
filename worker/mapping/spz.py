"""Niantic SPZ: moved to `protocol.splats.spz` (torch-free, the gateway converts maps too); re-exported here."""

from protocol.splats.spz import COLOR_SCALE, HEADER, MAGIC, VERSION, decode_spz, encode_spz, fractional_bits_for

__all__ = ["COLOR_SCALE", "HEADER", "MAGIC", "VERSION", "decode_spz", "encode_spz", "fractional_bits_for"]
