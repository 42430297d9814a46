"""Incremental snapshots (issue 24 point 3): the trajectory's frame records are sealed into chunks written once beside
the snapshot, so a snapshot write does not grow with the session; restore joins the chunks back, also after a loop
correction or a revision of sealed frames; snapshots without chunks (format 1, and format 2 as written before
chunking) still restore. Real Redis (redis-server) for the store."""

from __future__ import annotations

import numpy as np
import pytest
import redis

from protocol import keys
from protocol.codec import pack, unpack
from service.redis_embedded import EmbeddedRedis
from worker.config import SlamConfig
from worker.data.frame import Frame
from worker.pipeline.snapshot import flat_snapshot
from worker.pipeline.trajectory import Trajectory
from worker.runtime.engine import PassthroughEngine, restore_engine
from worker.runtime.snapshots import SnapshotWriter, read_snapshot
from worker.slam import SlamSystem

CHUNK = 16


def _pose(i: int) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = [0.01 * i, 0.02 * np.sin(i / 7.0), 0.0]
    return pose


def _trajectory(frames: int, keyframes: int = 4, chunk: int = CHUNK) -> Trajectory:
    """`keyframes` keyframes in the first frames, then frames tied to the last one: a camera staying in a known
    scene, so only the frame count grows."""
    traj = Trajectory(chunk_frames=chunk)
    last = None
    for i in range(frames):
        is_kf = i < keyframes * 3 and i % 3 == 0
        if is_kf:
            traj.add_keyframe(i, _pose(i), reference=last)
            last = i
        traj.add_frame(i, i / 30.0, last, _pose(i), is_kf, 0)
    return traj


def _assert_same(a: Trajectory, b: Trajectory) -> None:
    assert a.revision == b.revision
    assert [r.index for r in a.frames] == [r.index for r in b.frames]
    for (ia, ta, pa), (ib, tb, pb) in zip(a.listing(), b.listing(), strict=True):
        assert (ia, ta) == (ib, tb)
        np.testing.assert_array_equal(pa, pb)
    assert a.chunk_revisions == b.chunk_revisions


def _writes(traj_frames: int, every: int = 8) -> list[int]:
    """Bytes of each chunked write (state + new chunks) when snapshotting every `every` frames of a stream."""
    stored: dict[int, int] = {}
    sizes = []
    traj = Trajectory(chunk_frames=CHUNK)
    last = None
    for i in range(traj_frames):
        is_kf = i < 12 and i % 3 == 0
        if is_kf:
            traj.add_keyframe(i, _pose(i), reference=last)
            last = i
        traj.add_frame(i, i / 30.0, last, _pose(i), is_kf, 0)
        if (i + 1) % every == 0:
            state, write = traj.chunked_state(stored)
            sizes.append(len(pack(state)) + sum(map(len, write.new.values())))
            stored.update({c: write.versions()[c] for c in write.new})
    return sizes


def test_chunked_write_size_stays_flat_while_the_full_state_grows() -> None:
    n = 128
    short, long = _writes(n), _writes(4 * n)
    assert max(long) <= max(short) + 64  # the same bound after 4x the frames (msgpack ints may take a byte more)
    assert long[-1] <= max(short) + 64
    full_short, full_long = (len(pack(_trajectory(f).state_dict())) for f in (n, 4 * n))
    assert full_long > 3 * full_short  # what each write carried before: it grows with the session


def test_restore_from_chunks_equals_the_full_state_after_corrections_and_revisions() -> None:
    traj = _trajectory(5 * CHUNK + 3)
    stored: dict[int, int] = {}
    state, write = traj.chunked_state(stored)
    assert sorted(write.new) == list(range(5)) and len(state["index"]) == 3
    stored.update(write.versions())
    # a loop correction moves keyframes only: no chunk is written again
    traj.update_keyframes({3: _pose(3) @ np.diag([1.0, 1.0, 1.0, 1.0]) + np.pad(np.full((3, 1), 0.05), ((0, 1),
                                                                                                      (3, 0)))})
    state, write = traj.chunked_state(stored)
    assert write.new == {}
    restored = Trajectory()
    restored.load_state_dict(Trajectory.joined_state(unpack(pack(state)), _all_chunks(traj, {})))
    _assert_same(traj, restored)
    # revising sealed frames (a pose source re-estimated them) rewrites only the chunk that holds them
    traj.revise_frames({CHUNK + 1: _pose(40), CHUNK + 2: _pose(41)})
    state, write = traj.chunked_state(stored)
    assert sorted(write.new) == [1] and write.versions()[1] == 1
    chunks = {**_all_chunks(traj, {}), 1: write.new[1]}
    restored = Trajectory()
    restored.load_state_dict(Trajectory.joined_state(unpack(pack(state)), chunks))
    _assert_same(traj, restored)
    np.testing.assert_allclose(restored.pose_at(CHUNK + 1), _pose(40), atol=1e-12)
    # a stale chunk (the version before the revision) is refused, never silently used
    stale = _all_chunks(_trajectory(5 * CHUNK + 3), {})
    with pytest.raises(ValueError, match="version"):
        Trajectory.joined_state(unpack(pack(state)), stale)
    with pytest.raises(ValueError, match="missing"):
        Trajectory.joined_state(unpack(pack(state)), {0: chunks[0]})


def test_chunks_written_before_frame_anchors_load_with_none() -> None:
    traj = _trajectory(2 * CHUNK + 3)
    state, write = traj.chunked_state({})
    strip = ("anchor", "anchored")
    old_chunks = {i: pack({k: v for k, v in unpack(raw).items() if k not in strip}) for i, raw in write.new.items()}
    old_state = {k: v for k, v in unpack(pack(state)).items() if k not in strip}
    restored = Trajectory()
    restored.load_state_dict(Trajectory.joined_state(old_state, old_chunks))
    _assert_same(traj, restored)
    assert {r.anchor for r in restored.frames} == {-1}


def _all_chunks(traj: Trajectory, stored: dict[int, int]) -> dict[int, bytes]:
    return traj.chunked_state(stored)[1].new


def _posed_frames(count: int) -> list[Frame]:
    """A hand-held camera hovering in one place (millimetres): the keyframes stay few, the frames grow."""
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    poses = [np.eye(4) for _ in range(count)]
    for i, pose in enumerate(poses):
        pose[:3, 3] = 0.001 * np.sin([i / 5.0, i / 7.0, i / 11.0])
    return [Frame(index=i, timestamp=i / 30.0, image=image, pose=poses[i]) for i in range(count)]


def _posed_system() -> SlamSystem:
    """Device poses, no mapping, no loop closure: a SlamSystem whose push is cheap. Its device clock is not
    measured: these frames hover in place, so it would measure (and carry its measurement in every snapshot) up to
    its last frame; the clock's own state is tested in tests/tracking/test_device_clock.py."""
    from worker.geometry import Intrinsics

    config = SlamConfig.preset("test", mapping={"enabled": False}, loop={"enabled": False},
                               tracking={"source": "device"}, frontend={"keyframe_every": 10**6},
                               input={"device_clock": {"mode": "off"}})
    return SlamSystem(config, intrinsics=Intrinsics(30.0, 30.0, 16.0, 12.0, 32, 24))


def test_slam_system_chunked_snapshot_restores_and_old_formats_still_do(monkeypatch) -> None:
    monkeypatch.setattr("worker.pipeline.trajectory.CHUNK_FRAMES", CHUNK)
    system = _posed_system()
    system.tracking_stage.trajectory.chunk_frames = CHUNK
    frames = _posed_frames(3 * CHUNK + 5)
    for frame in frames:
        system.push(frame)
    future = system.begin_snapshot(stored_chunks={})
    blob, write = future.result(), future.chunks
    assert sorted(write.new) == [0, 1, 2]
    restored = SlamSystem.restore(blob, write.new)
    _assert_same(system.tracking_stage.trajectory, restored.tracking_stage.trajectory)
    with pytest.raises(ValueError, match="missing"):
        SlamSystem.restore(blob, {})
    # old formats: a self-contained format-2 snapshot (as main wrote it) and a format-1 one (one flat dict)
    full = system.snapshot()
    _assert_same(system.tracking_stage.trajectory, SlamSystem.restore(full).tracking_stage.trajectory)
    flat = {**flat_snapshot(unpack(full)), "format": "flashmono.slam/1"}
    flat["trajectory"] = {k: v for k, v in flat["trajectory"].items() if k not in ("chunk_frames", "chunk_revisions")}
    _assert_same(system.tracking_stage.trajectory, SlamSystem.restore(pack(flat)).tracking_stage.trajectory)
    system.close()


@pytest.fixture(scope="module")
def client():
    with EmbeddedRedis() as server:
        yield redis.Redis.from_url(server.url)


def _session(client: redis.Redis, sid: str, worker: str) -> None:
    client.hset(keys.session(sid), mapping={"id": sid, "status": "streaming"})
    client.set(keys.lease(sid), worker)
    for seq in range(4 * 4 * CHUNK):
        client.xadd(keys.inbox(sid), {"seq": seq})


def test_store_writes_flat_and_reads_back_what_restore_needs(client, monkeypatch) -> None:
    """SlamSystem snapshots through SnapshotWriter into Redis: the write size stays flat from N to 4N frames, and
    read_snapshot + restore gives the full trajectory, also to a new owner that continues and writes again. Arrays
    from 64 bytes are kept outside (the default keeps only large ones out), so that path runs here too."""
    monkeypatch.setattr("protocol.codec.EXTERNAL_MIN_BYTES", 64)
    sid, worker = "chunkstore1", "worker-a"
    _session(client, sid, worker)
    system = _posed_system()
    system.tracking_stage.trajectory.chunk_frames = CHUNK
    writer = SnapshotWriter(client, sid, worker)
    entries = [e for e, _ in client.xrange(keys.inbox(sid))]
    sizes: dict[int, int] = {}
    for frame in _posed_frames(4 * 4 * CHUNK):
        system.push(frame)
        if (frame.index + 1) % (CHUNK // 2) == 0:
            future = system.begin_snapshot(stored_chunks=dict(writer.stored_chunks))
            assert writer.write(future.result(), future.chunks, frame.index, entries[frame.index], "slam", "t") == 1
            sizes[frame.index + 1] = writer.last_write_bytes
    n = 4 * CHUNK
    early = max(v for k, v in sizes.items() if k <= n)
    late = max(v for k, v in sizes.items() if k > 3 * n)
    assert late <= early + 64, sizes
    snap = read_snapshot(client, sid)
    assert snap.seq == 4 * 4 * CHUNK - 1 and sorted(k for k in snap.chunks if isinstance(k, int)) == list(range(16))
    # arrays the newest snapshot no longer names were removed with its write: only its own parts are left
    assert snap.arrays and client.hlen(keys.snapshot_chunks(sid)) == 16 + len(snap.arrays)
    restored = restore_engine("slam", snap.data, snap.chunks)
    _assert_same(system.tracking_stage.trajectory, restored.tracking_stage.trajectory)
    # the new owner knows which chunks are stored: its next write adds none of them again
    writer_b = SnapshotWriter(client, sid, worker)
    writer_b.restored(snap)
    future = restored.begin_snapshot(stored_chunks=dict(writer_b.stored_chunks))
    assert future.result() and future.chunks.new == {}
    # a worker without the lease stores nothing
    client.set(keys.lease(sid), "worker-b")
    assert writer.write(future.result(), future.chunks, 0, entries[0], "slam", "t") == -2
    # a self-contained snapshot (finish) drops the manifest: it is read without chunks
    client.set(keys.lease(sid), worker)
    assert writer.write(system.snapshot(), None, 99, entries[-1], "slam", "t") == 1
    assert read_snapshot(client, sid).chunks == {}
    system.close()
    restored.close()


def test_large_arrays_kept_outside_by_digest() -> None:
    big, small = np.arange(20000, dtype=np.float32), np.ones(3)
    store: dict[str, bytes] = {}
    data = pack({"big": big, "again": [big], "small": small}, external=store)
    assert len(store) == 1 and len(data) < 200  # one digest for the same content, the small array inline
    out = unpack(data, external=store)
    np.testing.assert_array_equal(out["big"], big)
    np.testing.assert_array_equal(out["again"][0], big)
    with pytest.raises(ValueError, match="missing"):
        unpack(data, external={})
    with pytest.raises(ValueError):  # a reference in bytes read without a store (e.g. a client's frame) is refused
        unpack(data)


def test_incremental_slam_snapshot_does_not_write_unchanged_keyframe_data_again(data_dir, monkeypatch) -> None:
    """RGB-D with mapping and loop closure: a second snapshot names the first one's unchanged arrays (keyframe
    depth, images) by digest and carries only what changed; restore from the stored parts works."""
    from worker.data import open_source

    monkeypatch.setattr("protocol.codec.EXTERNAL_MIN_BYTES", 4096)
    frames = list(open_source(data_dir / "icl_mini", max_frames=8, resize=(96, 72), use_gt_depth=True))
    system = SlamSystem(SlamConfig.preset("test", mapping={"refine_iterations": 1}), intrinsics=frames[0].intrinsics)
    for frame in frames[:4]:
        system.push(frame)
    first = system.begin_snapshot(stored_chunks={})
    first_blob, first_write = first.result(), first.chunks
    for frame in frames[4:]:
        system.push(frame)
    second = system.begin_snapshot(stored_chunks={})
    blob, write = second.result(), second.chunks
    kept = set(first_write.arrays) & set(write.arrays)
    assert kept, "keyframe data of the first snapshot should be named again, not changed"
    new_bytes = sum(len(v) for d, v in write.arrays.items() if d not in first_write.arrays)
    assert len(blob) + new_bytes < len(system.snapshot())  # the incremental write is smaller than a whole one
    restored = SlamSystem.restore(blob, {**write.arrays, **write.new})
    assert restored.num_gaussians == system.num_gaussians > 0
    _assert_same(system.tracking_stage.trajectory, restored.tracking_stage.trajectory)
    with pytest.raises(ValueError, match="missing"):
        SlamSystem.restore(blob, dict(write.new))
    assert first_blob
    system.close()
    restored.close()


def test_passthrough_engine_chunked_snapshot_round_trip() -> None:
    engine = PassthroughEngine()
    for i in range(21):
        engine.push(Frame(index=i, timestamp=i / 30.0, image=np.zeros((4, 4, 3), np.uint8), pose=_pose(i)))
    snap = engine.begin_snapshot({0: 0})
    assert sorted(snap.chunks.new) == [1] and snap.chunks.manifest["sealed"] == 2
    chunks = {0: engine.begin_snapshot({}).chunks.new[0], **snap.chunks.new}
    restored = PassthroughEngine.restore(snap.result(), chunks)
    assert [i for i, _, _ in restored.trajectory()] == list(range(21))
    with pytest.raises(ValueError, match="missing"):
        PassthroughEngine.restore(snap.result(), {1: chunks[1]})
