"""The local stack can run its workers below the gateway's CPU priority (co-located deployments)."""

from __future__ import annotations

import os

import pytest
from runtime_helpers import WORKER_ENV

from service.launcher import LocalStack, start_worker_process


def test_workers_run_at_the_requested_nice_level_and_the_gateway_does_not():
    own = os.getpriority(os.PRIO_PROCESS, 0)
    if own > 7:
        pytest.skip(f"this test process already runs at nice {own}")
    with LocalStack(workers=1, worker_env=WORKER_ENV, worker_nice=7) as stack:  # ready: the worker heartbeats
        assert os.getpriority(os.PRIO_PROCESS, stack.workers[0].pid) == 7
        assert os.getpriority(os.PRIO_PROCESS, stack.gateway.pid) == own


def test_out_of_range_nice_is_refused_before_anything_starts():
    with pytest.raises(ValueError, match="nice must be within 0..19"):
        start_worker_process("redis://127.0.0.1:1/0", nice=25)
