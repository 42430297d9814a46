"""The bag of hidden states (paper 4.2): the final hidden state M_a of every closed submap and its keyframes."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import torch

from protocol.codec import pack, unpack
from worker.frontend.types import HiddenState


@dataclass
class BagEntry:
    submap_id: int
    state: HiddenState
    keyframe_ids: list[int]


class HiddenStateBag:
    """In-memory long-term memory: submap id -> (final state, keyframes). Serialises to msgpack bytes (fp16)."""

    def __init__(self) -> None:
        self._entries: dict[int, BagEntry] = {}
        self._submap_of_keyframe: dict[int, int] = {}

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, submap_id: int) -> bool:
        return submap_id in self._entries

    def add(self, submap_id: int, state: HiddenState, keyframe_ids: Iterable[int]) -> None:
        """Cache the final state of submap `submap_id` (detached copy) covering `keyframe_ids`."""
        keyframe_ids = [int(k) for k in keyframe_ids]
        if submap_id in self._entries:
            raise ValueError(f"submap {submap_id} is already in the bag")
        for k in keyframe_ids:
            if k in self._submap_of_keyframe:
                raise ValueError(f"keyframe {k} already belongs to submap {self._submap_of_keyframe[k]}")
        detached = HiddenState(state.state_tokens.detach().clone(), state.pose_memory.detach().clone(),
                               state.frames_seen)
        self._entries[int(submap_id)] = BagEntry(int(submap_id), detached, keyframe_ids)
        self._submap_of_keyframe.update({k: int(submap_id) for k in keyframe_ids})

    def add_finished(self, finished: Iterable) -> None:
        """Add the tracker's `FinishedSubmap`s (anything with submap_id, state, keyframe_ids)."""
        for f in finished:
            self.add(f.submap_id, f.state, f.keyframe_ids)

    def entry(self, submap_id: int) -> BagEntry:
        if submap_id not in self._entries:
            raise ValueError(f"no hidden state cached for submap {submap_id}")
        return self._entries[submap_id]

    def submap_of(self, keyframe_id: int) -> int | None:
        """The closed submap a keyframe belongs to (None while its submap is still open)."""
        return self._submap_of_keyframe.get(int(keyframe_id))

    def state_for_keyframe(self, keyframe_id: int) -> tuple[int, HiddenState]:
        """(submap id, cached state M_a) for keyframe i; ValueError when its submap is not in the bag."""
        submap = self.submap_of(keyframe_id)
        if submap is None:
            raise ValueError(f"keyframe {keyframe_id} belongs to no submap in the bag")
        return submap, self._entries[submap].state

    def keyframes(self) -> list[int]:
        return sorted(self._submap_of_keyframe)

    def nbytes(self) -> int:
        return sum(e.state.nbytes() for e in self._entries.values())

    def to_bytes(self, dtype: torch.dtype = torch.float16) -> bytes:
        """msgpack bytes; each state stored with HiddenState.to_bytes(dtype) (fp16 by default)."""
        return pack([{"submap_id": e.submap_id, "keyframe_ids": e.keyframe_ids, "state": e.state.to_bytes(dtype)}
                     for e in self._entries.values()])

    @classmethod
    def from_bytes(cls, data: bytes, dtype: torch.dtype = torch.float32, device: str = "cpu") -> HiddenStateBag:
        bag = cls()
        items = unpack(data)
        if not isinstance(items, list):
            raise ValueError("hidden-state bag bytes must hold a list of entries")
        for item in items:
            bag.add(int(item["submap_id"]), HiddenState.from_bytes(item["state"], dtype, device),
                    [int(k) for k in item["keyframe_ids"]])
        return bag
