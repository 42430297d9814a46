"""The contract between a chunked snapshot and its store: the parts of a session's state that only grow (the
trajectory's frame records) are sealed into fixed-size chunks, each written once beside the snapshot, so a snapshot
write does not grow with the session. Torch-free: the runtime's store reads manifests too.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any


@dataclass
class ChunkWrite:
    """What a chunked snapshot needs beside its bytes: `manifest` ({"frames": records per chunk, "sealed": chunk
    count, "versions": {chunk: version} of the chunks revised after they were sealed}) and the chunks the store
    does not hold yet (`new`: chunk -> bytes)."""

    manifest: dict[str, Any]
    new: dict[int, bytes] = field(default_factory=dict)

    def versions(self) -> dict[int, int]:
        """The version of every sealed chunk the snapshot needs."""
        return chunk_versions(self.manifest)


def chunk_versions(manifest: Mapping[str, Any]) -> dict[int, int]:
    """{chunk: version} of every sealed chunk a manifest lists (unrevised chunks are at version 0)."""
    revised = {int(k): int(v) for k, v in (manifest.get("versions") or {}).items()}
    return {i: revised.get(i, 0) for i in range(int(manifest["sealed"]))}
