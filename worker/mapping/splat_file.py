"""antimatter15's .splat: moved to `protocol.splats.splat_file` (torch-free, the gateway converts maps too);
re-exported here."""

from protocol.splats.splat_file import RECORD, decode_splat, encode_splat

__all__ = ["RECORD", "decode_splat", "encode_splat"]
