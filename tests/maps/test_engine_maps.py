"""The workers' side of maps (worker.maps): a finished session's map packaged and loaded back renders as the original
did, its keyframes, ids and surfel bindings kept; the `map_package` request; packages by version in Redis."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import redis
import torch

from protocol import keys
from protocol.map_package import CONTENT_TYPE, decode_package
from protocol.map_store import MapNotFound
from service.redis_embedded import EmbeddedRedis
from worker.config import SlamConfig
from worker.data import open_source
from worker.maps import add_version, build_package, load_gaussian_map, read_package
from worker.maps.session_in_map import SessionInMap
from worker.runtime.engine import PassthroughEngine
from worker.runtime.requests import RequestError, serve_request
from worker.slam import SlamSystem

DATA = Path(__file__).parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def finished() -> SlamSystem:
    """A real RGB-D session on 12 ICL frames at 160x120; the map keeps 1 archived photo, so a keyframe's goes."""
    frames = list(open_source(DATA, max_frames=12, resize=(160, 120), use_gt_depth=True))
    system = SlamSystem(SlamConfig.preset("rgbd", threaded=False, mapping={"final_refine_budget_s": 0,
                                                                           "archived_images": 1}))
    for frame in frames:
        system.push(frame)
    system.finish()
    return system


def test_a_packaged_map_loads_back_and_renders_as_the_original(finished):
    original = finished.mapping_stage.map
    package = decode_package(build_package(finished, "living room", ["s1"]))
    meta = package.meta()
    assert meta["name"] == "living room" and meta["sessions"] == ["s1"]
    assert meta["scale"] == "metric" and meta["mode"] == "rgbd"  # sensor depth: metres
    assert meta["keyframes"] == len(original.keyframe_ids) >= 4 and meta["surfels"] == original.num_gaussians
    assert [kf.id for kf in package.keyframes] == original.keyframe_ids
    assert sum(kf.rendered for kf in package.keyframes) == len(original.keyframe_ids) - original.held_images >= 1

    loaded = load_gaussian_map(package)
    assert loaded.keyframe_ids == original.keyframe_ids and loaded.held_images == len(original.keyframe_ids)
    assert torch.equal(loaded.surfels.keyframe_ids, original.surfels.keyframe_ids)
    camera = meta["camera"]
    K = torch.tensor([[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1]])
    for kf_id in original.keyframe_ids:
        pose = original.keyframe_pose(kf_id)
        assert torch.equal(loaded.keyframe_pose(kf_id), pose)
        assert torch.allclose(loaded.keyframe_exposure(kf_id), original.keyframe_exposure(kf_id))
        a, b = original.render(pose, K, 160, 120), loaded.render(pose, K, 160, 120)
        assert float((a.rgb - b.rgb).abs().max()) < 1e-3 and float((a.depth - b.depth).abs().max()) < 1e-3


def test_a_loaded_maps_surfels_still_move_with_their_keyframes(finished):
    loaded = load_gaussian_map(decode_package(build_package(finished, "m", [])))
    kf_id = loaded.keyframe_ids[-1]
    moved = loaded.keyframe_pose(kf_id).clone()
    moved[:3, 3] += torch.tensor([0.5, 0.0, 0.0], dtype=moved.dtype)
    own = loaded.surfels.keyframe_ids == kf_id
    before = loaded.surfels.means.clone()
    loaded.apply_pose_updates({kf_id: moved})
    shift = loaded.surfels.means - before
    assert torch.allclose(shift[own], torch.tensor([0.5, 0.0, 0.0]), atol=1e-4) and bool(own.any())
    assert float(shift[~own].abs().max()) == 0.0


def test_the_map_package_request_serves_the_engines_package_and_passthrough_refuses(finished):
    content_type, body = serve_request(finished, "map_package", {"name": "kitchen", "session_ids": ["a", "b"]})
    assert content_type == CONTENT_TYPE == "application/x-flashmono-map"
    assert decode_package(body).meta()["sessions"] == ["a", "b"]
    with pytest.raises(RequestError, match="keeps no map") as refused:
        serve_request(PassthroughEngine(), "map_package", {"name": "x", "session_ids": []})
    assert refused.value.status == 409


def test_versions_of_a_map_in_redis(finished):
    package = build_package(finished, "v", ["s1"])
    with EmbeddedRedis() as server:
        client = redis.Redis.from_url(server.url)
        with pytest.raises(MapNotFound):
            add_version(client, "nomap", package, "s1")  # the gateway creates maps; workers add versions
        client.hset(keys.map_record("m1"), mapping={"id": "m1", "versions": 0, "latest": 0})
        assert add_version(client, "m1", package, "s1") == 1
        assert add_version(client, "m1", package[:-1] + package[-1:], "s2") == 2
        assert read_package(client, "m1") == read_package(client, "m1", 1) == package
        record = {k.decode(): v.decode() for k, v in client.hgetall(keys.map_record("m1")).items()}
        assert record["latest"] == "2" and record["v2.session_id"] == "s2" and int(record["v1.size"]) == len(package)
        with pytest.raises(MapNotFound):
            read_package(client, "m1", 3)
        with pytest.raises(ValueError):
            add_version(client, "m1", b"not a package", "s3")
        client.delete(*keys.all_map_keys("m1"))
        with pytest.raises(MapNotFound):
            read_package(client, "m1")


def test_an_rgb_only_session_meets_a_saved_map_at_the_scale_its_depth_measures(finished):
    """Up to scale, the session's odometry points against the stored map's rendered depth give its scale in the
    map from a single frame (`SessionInMap.depth_scale`); it agrees with the similarity the anchoring settles on,
    and no frame is looked up before the odometry has points (its poses have no scale yet)."""
    package = decode_package(build_package(finished, "living room", ["s1"]))
    in_map = SessionInMap.from_package("m", 1, "localize", package)
    frames = list(open_source(DATA, max_frames=30, resize=(160, 120), use_gt_depth=False))
    system = SlamSystem(SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": False}),
                        intrinsics=frames[0].intrinsics, in_map=in_map)
    results = [system.push(f) for f in frames]
    assert in_map.anchored
    first_keyframes = [r.index for r in results if r.is_keyframe][:2]
    looked_up = [o.frame for o in in_map.anchoring.observations]
    assert min(looked_up) >= first_keyframes[1] > first_keyframes[0] == 0  # not the first keyframe: no points yet
    scales = [o.scale for o in in_map.anchoring.observations if o.scale is not None]
    anchored_scale = float(np.cbrt(np.linalg.det(in_map.anchoring.transform[:3, :3])))
    assert scales and all(abs(np.log(s / anchored_scale)) < np.log(1.15) for s in scales)
    system.finish()
