"""worker.native builds once per source/flags/compiler, reuses the cache, and reports a failed build; the depth
source then falls back to its numpy reference."""

from __future__ import annotations

import ctypes
from pathlib import Path

from native_fallback import run_without_compiler

from worker import native

REPO = Path(__file__).resolve().parents[2]


def _declare(lib: ctypes.CDLL) -> None:
    lib.twice.argtypes = [ctypes.c_int]
    lib.twice.restype = ctypes.c_int


def test_builds_once_and_reuses_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FLASHMONO_EXT_DIR", str(tmp_path / "cache"))
    source = tmp_path / "twice.cpp"
    source.write_text('extern "C" int twice(int x) { return 2 * x; }\n')
    lib = native.NativeLibrary("twice", source, _declare)
    assert lib.available() and lib.error is None
    assert lib.library.twice(21) == 42
    built = sorted((tmp_path / "cache").glob("flashmono_twice_*.so"))
    assert len(built) == 1
    stamp = built[0].stat().st_mtime_ns
    assert native.build("twice", source) == built[0] and built[0].stat().st_mtime_ns == stamp  # cached
    source.write_text('extern "C" int twice(int x) { return x + x; }\n')
    assert native.build("twice", source) != built[0]  # a new source hashes to a new library


def test_a_failed_build_is_reported_once(tmp_path, monkeypatch):
    monkeypatch.setenv("FLASHMONO_EXT_DIR", str(tmp_path))
    source = tmp_path / "broken.cpp"
    source.write_text("this is not C++\n")
    lib = native.NativeLibrary("broken", source, _declare)
    assert not lib.available()
    assert "compiling broken.cpp failed" in lib.error
    assert lib.load() is None and list(tmp_path.glob("*.so")) == []


def test_depth_falls_back_to_the_reference_without_a_compiler(tmp_path):
    script = (
        "import logging, sys, numpy as np\n"
        "sys.path.insert(0, 'tests/depth')\n"
        "logging.basicConfig(level=logging.WARNING)\n"
        "from scenes import Scene, pinhole, translation\n"
        "from worker.depth import estimate_depth, mvs_cpu\n"
        "K = pinhole(48, 36)\n"
        "scene = Scene(texel=0.03)\n"
        "views = [(scene.render(p, K, 48, 36)[0], p) for p in (translation(-0.3), translation(0.3))]\n"
        "est = estimate_depth(scene.render(np.eye(4), K, 48, 36)[0], K, np.eye(4), views, (1.0, 4.0))\n"
        "assert not mvs_cpu.available() and est.backend == 'reference', est.backend\n"
        "assert est.coverage > 0.5, est.coverage\n"
        "print('FELL BACK', mvs_cpu.load_error())\n"
    )
    result = run_without_compiler(script, tmp_path)
    assert "FELL BACK" in result.stdout
    assert "compiled MVS kernels unavailable" in result.stderr
