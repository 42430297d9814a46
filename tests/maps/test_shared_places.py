"""Sessions mapping one map together share their new places live: a session whose frames the saved map does not
hold finds them among the places another session added, through the map's live stream in a real Redis."""

from __future__ import annotations

import numpy as np
import pytest
import redis

from service.redis_embedded import EmbeddedRedis
from worker.maps.session_in_map import SessionInMap
from worker.runtime.map_exchange import MapExchange
from worker.slam import SlamConfig, SlamSystem

from .conftest import views_of


@pytest.fixture(scope="module")
def client():
    server = EmbeddedRedis().start()
    try:
        yield redis.Redis.from_url(server.url)
    finally:
        server.stop()


def _extend_session(frames, views) -> tuple[SlamSystem, SessionInMap]:
    in_map = SessionInMap("room", 1, "extend", lambda: views, map_metric=True)
    config = SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": False})
    return SlamSystem(config, intrinsics=frames[0].intrinsics, in_map=in_map), in_map


def _relocalized(results) -> list:
    return [e for r in results for e in r.events if type(e).__name__ == "Relocalized"]


def test_a_session_finds_itself_among_the_places_another_one_added(icl_frames, client) -> None:
    saved = views_of(icl_frames[:8:2])  # the saved map holds the start of the room only (frames 0-12 match it)
    first, first_map = _extend_session(icl_frames, saved)
    first_side = MapExchange(client, "first", first_map)
    for frame in icl_frames[:44]:  # from the saved part on into the rest of the room
        result = first.push(frame)
        first_side.exchange(result.is_keyframe)
    assert first_map.anchored and client.xlen(first_side.stream) > 5
    published_by_first = client.xlen(first_side.stream)

    later = icl_frames[24:40]  # a part the saved map does not hold
    alone, alone_map = _extend_session(later, saved)
    assert not _relocalized([alone.push(f) for f in later]) and not alone_map.anchored

    second, second_map = _extend_session(later, saved)
    second_side = MapExchange(client, "second", second_map)
    results = []
    for frame in later:
        second_side.exchange(keyframe=True)
        results.append(second.push(frame))
    assert second_map.shared_received == published_by_first  # every place of the first's, none of its own
    assert client.xlen(first_side.stream) > published_by_first  # and, anchored, it shares its own
    assert len(_relocalized(results)) == 1
    # its fixes came from the first session's places (a loop between two devices), counted as such
    assert second_map.shared_fixes > 0 and first_map.shared_fixes == 0 == alone_map.shared_fixes
    assert second_map.stats()["map_shared_fixes"] == second_map.shared_fixes
    errors = [np.linalg.norm(pose[:3, 3] - icl_frames[i].gt_pose[:3, 3]) for i, _, pose in second.trajectory()]
    assert max(errors) < 0.06  # in the map's world
