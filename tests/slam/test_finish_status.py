"""finish() tells where it is (worker.pipeline.finish_status): the mapping backlog draining, the final refinement's
steps, an estimate of the time left; `flashmono run` shows it, the worker sends it in `finishing` messages."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from worker.config import SlamConfig
from worker.data import Frame, open_source
from worker.offline import run_sequence
from worker.pipeline.finish_status import FinishStatus
from worker.slam import SlamSystem

DATA = Path(__file__).parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(open_source(DATA, max_frames=12, resize=(80, 60), use_gt_depth=True))


def test_the_status_counts_work_and_estimates_the_time_left():
    status = FinishStatus()
    assert status.as_dict()["phase"] is None and status.eta_s() is None
    status.begin("refining", 10)
    assert status.eta_s() is None  # no pace yet
    time.sleep(0.05)
    status.step(5)
    eta = status.eta_s()
    assert status.done == 5 and eta is not None and 0.02 < eta < 1.0  # as long again as the first half took
    status.begin("refining", 1000, deadline=time.perf_counter() + 0.2)
    status.step()
    assert status.eta_s() <= 0.2  # a deadline bounds the estimate
    left = [3]
    status.begin("mapping", 3, done=lambda: 3 - left[0])
    left[0] = 1
    assert status.done == 2
    status.begin("done", 0)
    assert status.eta_s() == 0.0
    with pytest.raises(ValueError):
        status.begin("napping", 1)


def test_finish_reports_the_drain_then_the_refinement(frames):
    config = SlamConfig.preset("test", input={"surfel_init": "depth"}, frontend={"keyframe_every": 2},
                               threaded=True, queue_size=64,
                               mapping={"shed_backlog": 0, "final_refine_passes": 3, "final_refine_budget_s": 0})
    system = SlamSystem(config)
    seen: list[dict] = []
    with system.mapping_stage.lock:  # mapping stalls: finish() starts with a backlog
        for frame in frames:
            system.push(frame)
        backlog = system.mapping_stage.pending
    stop = threading.Event()

    def watch() -> None:
        while not stop.is_set():
            seen.append(system.finish_status.as_dict())
            time.sleep(0.002)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    system.finish()
    stop.set()
    watcher.join()
    seen.append(system.finish_status.as_dict())
    phases = [s["phase"] for s in seen if s["phase"]]
    order = [p for i, p in enumerate(phases) if i == 0 or phases[i - 1] != p]
    assert order[0] == "mapping" and order[-1] == "done" and "refining" in order
    mapping = [s for s in seen if s["phase"] == "mapping"]
    assert backlog >= 3 and mapping[0]["total"] >= backlog - 1
    refining = [s for s in seen if s["phase"] == "refining"]
    assert refining[-1]["total"] == 3 * system.mapping_stage.map.held_images > 0
    assert max(s["done"] for s in refining) > 0
    assert system.finish_status.as_dict()["phase"] == "done"


@pytest.mark.parametrize("counts_drain", [True, False])
def test_an_offline_budget_is_the_refinement_s_own(frames, counts_drain):
    """A live session's budget covers its whole finish (a slow drain leaves the refinement nothing); an offline
    run's covers the refinement alone, after a drain however long."""
    config = SlamConfig.preset("test", input={"surfel_init": "depth"}, frontend={"keyframe_every": 2},
                               threaded=True, queue_size=64,
                               mapping={"shed_backlog": 0, "final_refine_passes": 50, "final_refine_budget_s": 0.4,
                                        "final_refine_budget_counts_drain": counts_drain})
    system = SlamSystem(config)
    with system.mapping_stage.lock:
        for frame in frames:
            system.push(frame)
    held = threading.Event()

    def hold_the_map() -> None:  # the drain waits 0.8 s: twice the budget
        with system.mapping_stage.lock:
            held.set()
            time.sleep(0.8)

    holder = threading.Thread(target=hold_the_map, daemon=True)
    holder.start()
    held.wait(10)
    steps = []
    system.finish_status.step = lambda units=1: steps.append(units)
    system.finish()
    holder.join()
    assert (len(steps) > 0) is not counts_drain


def test_an_offline_run_reports_its_finish(tmp_path):
    reports: list[dict] = []
    config = SlamConfig.preset("test", input={"surfel_init": "depth"}, mapping={"final_refine_passes": 2})
    run_sequence(DATA, tmp_path, config, use_gt_depth=True, max_frames=8, resize=(80, 60),
                 finish_progress=reports.append)
    assert reports and reports[-1]["phase"] == "done" and reports[-1]["eta_s"] == 0.0
