"""The map package format (protocol.map_package): a round trip keeps every field, the metadata is computed from the
content, and corrupt bytes of any kind give a MapPackageError that says what is wrong, never another exception."""

from __future__ import annotations

import dataclasses
import re

import msgpack
import numpy as np
import pytest
from map_samples import synthetic_package, synthetic_package_bytes

from protocol.codec import pack, unpack
from protocol.map_package import FORMAT, MapPackageError, decode_package, encode_package, package_meta


def test_a_package_round_trips_every_field():
    package = synthetic_package(keyframes=4, surfels=300)
    package.keyframes[1].depth = None
    package.keyframes[2].exposure = np.arange(6, dtype=np.float32) / 10
    package.keyframes[3].rendered = True
    package.engine = {"voxel_size": 0.02, "background": {"face_cells": 4, "rgb": np.full((6, 4, 4, 3), 7, np.uint8),
                                                         "seen": np.ones((6, 4, 4), bool)}}
    back = decode_package(encode_package(package))
    assert (back.name, back.scale, back.mode, back.sessions, back.created_at) == (
        package.name, package.scale, package.mode, package.sessions, package.created_at)
    assert back.surfels_ply == package.surfels_ply
    for mine, theirs in zip(package.keyframes, back.keyframes, strict=True):
        assert (mine.id, mine.width, mine.height, mine.jpeg, mine.rendered) == (
            theirs.id, theirs.width, theirs.height, theirs.jpeg, theirs.rendered)
        np.testing.assert_array_equal(mine.pose, theirs.pose)
        np.testing.assert_array_equal(mine.K, theirs.K)
        assert (mine.depth is None) == (theirs.depth is None) and (mine.exposure is None) == (theirs.exposure is None)
    np.testing.assert_array_equal(back.keyframes[0].depth, package.keyframes[0].depth)
    assert back.engine["voxel_size"] == 0.02 and back.engine["background"]["rgb"].shape == (6, 4, 4, 3)


def test_the_metadata_is_computed_from_the_content_not_read_from_the_file():
    data = synthetic_package_bytes(keyframes=3, surfels=1000)
    meta = package_meta(data)
    assert meta["name"] == "synthetic" and meta["keyframes"] == 3 and meta["surfels"] == 1000
    assert meta["scale"] == "metric" and meta["mode"] == "rgbd" and meta["sessions"] == ["s" * 32]
    assert meta["camera"] == {"width": 32, "height": 24, "fx": 30.0, "fy": 30.0, "cx": 16.0, "cy": 12.0}
    low, high = np.asarray(meta["bounds"]["min"]), np.asarray(meta["bounds"]["max"])
    assert np.all(high - low > 3.0) and np.all(high - low < 6.0)  # +-2.3 sigma of N(axis, 1), not the extremes
    doc = unpack(data)
    doc["meta"].update(surfels=5, keyframes=99, bounds={"min": [0, 0, 0], "max": [1, 1, 1]})
    assert package_meta(pack(doc)) == meta  # what the file claims is recomputed


def test_a_stray_surfel_does_not_blow_up_the_bounds():
    package = synthetic_package(surfels=500)
    from protocol.splats.ply_records import read_vertex_records, write_vertex_records

    records = read_vertex_records(package.surfels_ply).copy()
    records["x"][0] = 1e6
    package.surfels_ply = write_vertex_records(records)
    assert decode_package(encode_package(package)).meta()["bounds"]["max"][0] < 10


def test_encode_refuses_what_decode_would_refuse():
    package = synthetic_package()
    with pytest.raises(MapPackageError, match="no keyframes"):
        encode_package(dataclasses.replace(package, keyframes=[]))
    with pytest.raises(MapPackageError, match="scale"):
        encode_package(dataclasses.replace(package, scale="furlongs"))
    package.keyframes[0].pose = package.keyframes[0].pose.copy()
    package.keyframes[0].pose[0, 0] = np.nan
    with pytest.raises(MapPackageError, match="keyframe 0: the pose"):
        encode_package(package)


def _edited(change) -> bytes:
    doc = unpack(synthetic_package_bytes())
    change(doc)
    return pack(doc)


@pytest.mark.parametrize(("data", "message"), [
    (b"", "msgpack"),
    (b"\x00not msgpack at all", "msgpack"),
    (msgpack.packb([1, 2, 3]), "not a map"),
    (_edited(lambda d: d.update(format="flashmono.map/2")), "format"),
    (_edited(lambda d: d.pop("format")), "format"),
    (_edited(lambda d: d.pop("surfels_ply")), "'surfels_ply' is missing"),
    (_edited(lambda d: d.update(keyframes=[])), "no keyframes"),
    (_edited(lambda d: d["meta"].pop("name")), "'name' is missing"),
    (_edited(lambda d: d["keyframes"][0].pop("K")), "'K' is missing"),
    (_edited(lambda d: d["keyframes"][0].update(id=True)), "'id' has the wrong type"),
    (_edited(lambda d: d["keyframes"][1].update(id=0)), "share an id"),
    (_edited(lambda d: d["keyframes"][0].update(pose=np.eye(4, dtype=np.float32))), "float64 array of shape [4, 4]"),
    (_edited(lambda d: d["keyframes"][0].update(pose=np.full((4, 4), np.inf))), "finite camera-to-world"),
    (_edited(lambda d: d["keyframes"][0].update(pose=np.diag([1.0, 1.0, -1.0, 1.0]))), "similarity"),
    (_edited(lambda d: d["keyframes"][0].update(K=np.zeros((3, 3)))), "positive focal"),
    (_edited(lambda d: d["keyframes"][0].update(depth=np.zeros((12, 16), np.float32))), "float16 array"),
    (_edited(lambda d: d["keyframes"][0].update(depth=np.zeros((24, 32), np.float16))), "shape [12, 16]"),
    (_edited(lambda d: d["keyframes"][0].update(jpeg=b"GIF89a....")), "no JPEG"),
    (_edited(lambda d: d["keyframes"][0].update(width=64)), "not a 64x24 JPEG"),
    (_edited(lambda d: d.update(surfels_ply=b"not a ply")), "surfels_ply: not a readable PLY"),
    (_edited(lambda d: d.update(surfels_ply=d["surfels_ply"][:-10])), "truncated"),
    (_edited(lambda d: d.update(engine={"voxel_size": -1})), "voxel_size"),
    (_edited(lambda d: d.update(engine={"background": {"face_cells": 4, "rgb": np.zeros(3, np.uint8)}})),
     "background.rgb"),
])
def test_corrupt_packages_are_refused_with_what_is_wrong(data, message):
    with pytest.raises(MapPackageError, match=re.escape(message)):
        decode_package(data)


def test_surfels_must_be_bound_to_the_packages_keyframes():
    from map_samples import surfels_ply

    data = _edited(lambda d: d.update(surfels_ply=surfels_ply(10, [0, 77])))
    with pytest.raises(MapPackageError, match="keyframes the package does not have"):
        decode_package(data)


def test_sizes_over_the_limits_are_refused():
    data = synthetic_package_bytes()
    with pytest.raises(MapPackageError, match="over the limit"):
        decode_package(data, max_bytes=len(data) - 1)
    with pytest.raises(MapPackageError, match="bytes, not str"):
        decode_package("a string")  # type: ignore[arg-type]


def test_random_truncations_and_bit_flips_only_ever_raise_map_package_errors():
    data = synthetic_package_bytes(keyframes=2, surfels=40)
    rng = np.random.default_rng(7)
    decoded = refused = 0
    cases = [data[:cut] for cut in rng.integers(0, len(data), 150)]
    for _ in range(600):
        flipped = bytearray(data)
        for at in rng.integers(0, len(data), rng.integers(1, 4)):
            flipped[at] ^= 1 << int(rng.integers(0, 8))
        cases.append(bytes(flipped))
    for case in cases:
        try:
            decode_package(case)
            decoded += 1
        except MapPackageError:
            refused += 1
    assert refused >= 150 and decoded + refused == len(cases)  # every truncation is refused; some flips are harmless
    assert FORMAT.encode() in data
