"""The map in the formats web clients read: moved to `protocol.splats.formats` (torch-free, the gateway converts
maps too); re-exported here."""

from protocol.splats.formats import FORMATS, EncodedMap, encode_map

__all__ = ["FORMATS", "EncodedMap", "encode_map"]
