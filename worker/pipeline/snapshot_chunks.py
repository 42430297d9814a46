"""The contract between an incremental snapshot and its store. What only grows with a session (the trajectory's
frame records) is sealed into fixed-size chunks, each written once beside the snapshot; large arrays (keyframe
images and depth, the map's tensors) are kept outside the snapshot by content digest (protocol.codec's
`external`), so those that did not change since the last snapshot (every keyframe's own data) are not written
again. A snapshot write then carries the small state, the newest chunk and the changed arrays, however long the
session. Torch-free: the runtime's store reads manifests too.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any


@dataclass
class ChunkWrite:
    """What an incremental snapshot needs beside its bytes: `manifest` ({"frames": records per chunk, "sealed":
    chunk count, "versions": {chunk: version} of the chunks revised after they were sealed}), the chunks the store
    does not hold yet (`new`: chunk -> bytes) and the arrays it refers to (`arrays`, filled as the stages pack
    their parts: read it once the snapshot is complete)."""

    manifest: dict[str, Any]
    new: dict[int, bytes] = field(default_factory=dict)
    arrays: dict[str, bytes] = field(default_factory=dict)  # every array the snapshot refers to: digest -> packed

    def versions(self) -> dict[int, int]:
        """The version of every sealed chunk the snapshot needs."""
        return chunk_versions(self.manifest)


def chunk_versions(manifest: Mapping[str, Any]) -> dict[int, int]:
    """{chunk: version} of every sealed chunk a manifest lists (unrevised chunks are at version 0)."""
    revised = {int(k): int(v) for k, v in (manifest.get("versions") or {}).items()}
    return {i: revised.get(i, 0) for i in range(int(manifest["sealed"]))}
