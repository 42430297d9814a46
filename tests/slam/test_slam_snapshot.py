"""Snapshot/restore: a monocular run snapshotted at frame k, restored in another process and continued, ends with
the same trajectory and map size as the uninterrupted run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data import open_source
from worker.slam import SlamSystem

FRAMES = 4
SNAPSHOT_AT = 2  # after frames 0..1; the run crosses a submap boundary (submaps of 3) after the restore

CHILD = """
import json, sys
import numpy as np
from worker.data import open_source
from worker.slam import SlamSystem
snapshot_path, data_dir, start, count = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
system = SlamSystem.restore(open(snapshot_path, "rb").read())
frames = list(open_source(data_dir, max_frames=count, resize=(96, 72)))
for frame in frames[start:]:
    system.push(frame)
system.finish()
print(json.dumps({"poses": [p.tolist() for _, _, p in system.trajectory("all")],
                  "indices": [i for i, _, _ in system.trajectory("all")],
                  "num_gaussians": system.num_gaussians, "revision": system.revision}))
"""


def config() -> SlamConfig:
    return SlamConfig.preset("test", frontend={"submap_size": 3}, tracking={"source": "model"},
                             mapping={"refine_iterations": 1})


def test_restored_run_continues_identically(data_dir: Path, tmp_path: Path) -> None:
    frames = list(open_source(data_dir / "icl_mini", max_frames=FRAMES, resize=(96, 72)))
    system = SlamSystem(config())
    for frame in frames[:SNAPSHOT_AT]:
        system.push(frame)
    snapshot = system.snapshot()
    (tmp_path / "snap.msgpack").write_bytes(snapshot)
    for frame in frames[SNAPSHOT_AT:]:
        system.push(frame)
    system.finish()
    expected = np.stack([p for _, _, p in system.trajectory("all")])
    # the continuation must actually move the camera, or equality would prove nothing
    assert np.linalg.norm(expected[-1][:3, 3] - expected[SNAPSHOT_AT - 1][:3, 3]) > 1e-6

    repo = Path(__file__).resolve().parents[2]
    proc = subprocess.run([sys.executable, "-c", CHILD, str(tmp_path / "snap.msgpack"), str(data_dir / "icl_mini"),
                           str(SNAPSHOT_AT), str(FRAMES)], capture_output=True, text=True, cwd=repo, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    restored = json.loads(proc.stdout.strip().splitlines()[-1])
    assert restored["indices"] == [f.index for f in frames]
    np.testing.assert_allclose(np.asarray(restored["poses"]), expected, atol=1e-4)
    assert restored["num_gaussians"] == system.num_gaussians > 0
    assert restored["revision"] == system.revision


def test_restore_rejects_foreign_bytes() -> None:
    from protocol.codec import pack

    with pytest.raises(ValueError, match="not a Flash-Mono SLAM snapshot"):
        SlamSystem.restore(pack({"format": "something-else"}))
    with pytest.raises(ValueError):
        SlamSystem.restore(b"\x00garbage")
