"""An extend session's map joined to the stored map: every keyframe and surfel of the map kept, the session's
keyframes under new ids (their surfels follow), its surfels only where the map has none."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from map_samples import synthetic_package

from protocol.map_package import decode_package, encode_package
from protocol.splats.ply_records import read_vertex_records, write_vertex_records
from worker.maps.merge import merge_packages


def _moved(package, shift: float):
    """The package's surfels shifted by `shift` along x (a place the map has not seen when large)."""
    records = read_vertex_records(package.surfels_ply).copy()
    records["x"] += shift
    return replace(package, surfels_ply=write_vertex_records(records))


def test_a_session_adds_its_keyframes_under_new_ids_and_its_surfels_where_the_map_has_none() -> None:
    base = replace(synthetic_package(surfels=300, seed=1), engine={"voxel_size": 0.05})
    far = _moved(synthetic_package(surfels=300, seed=2), 100.0)  # another place entirely
    merged = merge_packages(base, far, "session-b")
    base_ids = [kf.id for kf in base.keyframes]
    new_ids = [kf.id for kf in merged.keyframes[len(base.keyframes):]]
    assert [kf.id for kf in merged.keyframes[: len(base.keyframes)]] == base_ids
    assert len(new_ids) == len(far.keyframes) and min(new_ids) > max(base_ids)
    records = read_vertex_records(merged.surfels_ply)
    assert len(records) == 600  # nothing overlaps
    assert set(records["keyframe_id"][300:].tolist()) <= set(new_ids)
    assert merged.sessions[-1] == "session-b"
    decoded = decode_package(encode_package(merged))  # a valid package: every surfel bound to a keyframe it has
    assert decoded.meta()["keyframes"] == len(base.keyframes) + len(far.keyframes)


def test_a_place_both_saw_keeps_the_maps_surfels_once() -> None:
    base = replace(synthetic_package(surfels=300, seed=1), engine={"voxel_size": 0.05})
    same = replace(synthetic_package(surfels=300, seed=1))  # the very same surfels, seen again
    merged = merge_packages(base, same, "session-c")
    records = read_vertex_records(merged.surfels_ply)
    assert len(records) == 300
    assert np.array_equal(records["x"], read_vertex_records(base.surfels_ply)["x"])
