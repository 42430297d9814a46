"""Bag of hidden states: caching, lookup by keyframe, fp16 bytes for Redis."""

from __future__ import annotations

import pytest
import torch

from worker.frontend.types import HiddenState
from worker.loop.bag import HiddenStateBag


def _state(seed: int) -> HiddenState:
    g = torch.Generator().manual_seed(seed)
    return HiddenState(torch.randn(1, 64, 32, generator=g), torch.randn(1, 16, 64, generator=g), frames_seen=8)


def test_lookup_by_keyframe_and_detached_copy():
    bag = HiddenStateBag()
    s0 = _state(0)
    bag.add(0, s0, [0, 3, 5])
    bag.add(1, _state(1), [7, 9])
    s0.state_tokens.add_(100.0)  # the caller mutating its state must not change the cached one
    submap, cached = bag.state_for_keyframe(5)
    assert submap == 0 and cached.frames_seen == 8
    assert torch.equal(cached.state_tokens, _state(0).state_tokens)
    assert bag.submap_of(9) == 1 and bag.submap_of(6) is None
    assert bag.keyframes() == [0, 3, 5, 7, 9]
    with pytest.raises(ValueError, match="no submap in the bag"):
        bag.state_for_keyframe(6)
    with pytest.raises(ValueError, match="already in the bag"):
        bag.add(1, _state(2), [11])
    with pytest.raises(ValueError, match="already belongs"):
        bag.add(2, _state(2), [9])


def test_bytes_are_fp16_and_round_trip():
    bag = HiddenStateBag()
    for k in range(3):
        bag.add(k, _state(k), [7 * k])
    data = bag.to_bytes()
    assert len(data) < 0.6 * bag.nbytes()  # fp16 payload: half of the fp32 tensors plus small headers
    restored = HiddenStateBag.from_bytes(data)
    assert len(restored) == 3 and restored.keyframes() == [0, 7, 14]
    for k in range(3):
        a, b = bag.entry(k).state, restored.entry(k).state
        assert b.state_tokens.dtype == torch.float32 and b.frames_seen == 8
        torch.testing.assert_close(a.state_tokens, b.state_tokens, atol=2e-3, rtol=1e-3)
        torch.testing.assert_close(a.pose_memory, b.pose_memory, atol=2e-3, rtol=1e-3)
    with pytest.raises(ValueError):
        HiddenStateBag.from_bytes(b"\x01\x02")
