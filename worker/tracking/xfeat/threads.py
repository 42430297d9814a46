"""Torch's thread count for the calling thread only, around a network pass."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


@contextlib.contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """Torch operators of the calling thread on `threads` threads (OpenMP's setting is per thread: other threads that
    have run torch operators, e.g. the mapping stage's, keep theirs; one running its first operator meanwhile starts
    with this count, as with `worker.mapping.refine`'s serial kernels). On 2 busy cores one thread is the fast choice
    for XFeat: two OpenMP threads wait for each other (a 320x240 pass took 100-1500 ms on two threads, 14-35 ms on
    one, at load 4)."""
    before = torch.get_num_threads()
    if threads == before:
        yield
        return
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)
