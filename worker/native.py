"""Compiled C++ kernels built on first use: one `NativeLibrary` per single-file source with a plain C ABI.

The first `load()` compiles the source with the system C++ compiler ($CXX, default c++) into $FLASHMONO_EXT_DIR
(default ~/.cache/flashmono/torch_extensions), keyed by a hash of the source, the flags and the compiler's version;
later loads (in any process) reuse the cached library. The caller owns every buffer and calls the kernels through
ctypes, which releases the GIL during a call. A failed build or load is remembered: `available()` is then False and
`error` says why, so callers can fall back to their reference implementation.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import subprocess
import tempfile
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

DEFAULT_FLAGS = ("-O3", "-std=c++17", "-fPIC", "-shared", "-pthread")


def extension_dir() -> Path:
    """Where compiled libraries are cached."""
    return Path(os.environ.get("FLASHMONO_EXT_DIR", Path.home() / ".cache" / "flashmono" / "torch_extensions"))


def compiler() -> list[str]:
    """The C++ compiler command ($CXX, default c++)."""
    return os.environ.get("CXX", "c++").split()


def build(name: str, source: Path, flags: Sequence[str] = DEFAULT_FLAGS) -> Path:
    """Compile `source` into a shared library unless one for this exact source, flags and compiler is cached.

    Returns the library's path; raises (CalledProcessError, FileNotFoundError, RuntimeError) when it cannot build.
    """
    command = compiler()
    version = subprocess.run([*command, "--version"], capture_output=True, text=True, check=True).stdout
    key = hashlib.sha256(source.read_bytes() + " ".join(flags).encode() + version.encode()).hexdigest()[:16]
    target = extension_dir() / f"flashmono_{name}_{key}.so"
    if target.exists():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        result = subprocess.run([*command, *flags, str(source), "-o", tmp], capture_output=True, text=True)
        if result.returncode != 0:
            raise RuntimeError(f"compiling {source.name} failed:\n{result.stderr[-4000:]}")
        os.replace(tmp, target)  # atomic: concurrent builders never see a half-written library
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target


class NativeLibrary:
    """A lazily compiled and loaded kernel library; `declare(lib)` sets the functions' argtypes and restypes."""

    def __init__(self, name: str, source: Path, declare: Callable[[ctypes.CDLL], None],
                 flags: Sequence[str] = DEFAULT_FLAGS) -> None:
        self.name = name
        self.source = Path(source)
        self.flags = tuple(flags)
        self._declare = declare
        self._lock = threading.Lock()
        self._library: ctypes.CDLL | None = None
        self._error: str | None = None
        self._tried = False

    def load(self) -> ctypes.CDLL | None:
        """The loaded library, building it on the first call; None when that failed (see `error`)."""
        with self._lock:
            if not self._tried:
                self._tried = True
                try:
                    library = ctypes.CDLL(str(build(self.name, self.source, self.flags)))
                    self._declare(library)
                    self._library = library
                except Exception as exc:  # no compiler, build error, unloadable library...
                    self._error = f"{type(exc).__name__}: {exc}"
            return self._library

    def available(self) -> bool:
        """True when the library compiled (or was cached) and loaded."""
        return self.load() is not None

    def require(self, what: str) -> ctypes.CDLL:
        """The loaded library; RuntimeError naming `what` and why when it is unavailable."""
        library = self.load()
        if library is None:
            raise RuntimeError(f"compiled {what} unavailable: {self._error}")
        return library

    @property
    def library(self) -> ctypes.CDLL | None:
        """The library once loaded (None before `load()` or after a failure)."""
        return self._library

    @property
    def error(self) -> str | None:
        """Why the library is unavailable (None when it loaded or was not tried yet)."""
        return self._error
