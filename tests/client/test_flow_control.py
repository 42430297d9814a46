"""The client's flow control: window of un-acked frames, bound on server-side pending frames, ordered recovery."""

from __future__ import annotations

import pytest

from client.errors import BackpressureError
from client.streaming import FlowControl


def test_window_bounds_unacknowledged_frames() -> None:
    flow = FlowControl(window=2, max_pending=10)
    flow.on_sent(0, "f0")
    assert flow.can_send()
    flow.on_sent(1, "f1")
    assert not flow.can_send()
    flow.on_ack(0, queue_depth=1)
    assert flow.can_send()
    assert flow.server_queue_depth == 1


def test_pending_frames_at_the_server_bound_sending_until_results_arrive() -> None:
    flow = FlowControl(window=4, max_pending=3)
    for seq in range(3):
        flow.on_sent(seq, seq)
        flow.on_ack(seq, queue_depth=seq + 1)
    assert not flow.can_send()  # 3 queued at the server, none processed
    flow.on_result(0)
    assert flow.can_send()
    assert flow.unsettled == 2


def test_result_before_ack_does_not_leave_a_phantom_pending_frame() -> None:
    flow = FlowControl(window=1, max_pending=1)
    flow.on_sent(0, "f0")
    flow.on_result(0)
    flow.on_ack(0, queue_depth=0)
    assert flow.unsettled == 0 and flow.can_send()


def test_refused_frames_are_resent_in_order_after_in_flight_frames_settle() -> None:
    flow = FlowControl(window=4, max_pending=8, backoff_s=0.01)
    for seq in range(4):
        flow.on_sent(seq, f"f{seq}")
    flow.on_ack(0, 1)
    flow.on_refused(1)
    assert not flow.can_send()  # recovery blocks new frames
    assert not flow.recovery_ready()  # 2 and 3 still unanswered
    flow.on_refused(2)
    flow.on_refused(3)
    assert flow.recovery_ready()
    resend, delay = flow.take_resends()
    assert resend == [(1, "f1"), (2, "f2"), (3, "f3")]  # re-sent under their own seqs
    assert delay == pytest.approx(0.01)  # the first round: no doubling yet
    assert flow.dropped == [] and flow.retries == 3
    assert flow.can_send()


def test_refused_frame_overtaken_by_an_accepted_one_is_dropped_not_reordered() -> None:
    flow = FlowControl(window=4, max_pending=8)
    for seq in range(3):
        flow.on_sent(seq, f"f{seq}")
    flow.on_refused(0)
    flow.on_ack(1, 7)  # a slot freed: frame 1 got in after 0 was refused
    flow.on_refused(2)
    resend, _ = flow.take_resends()
    assert resend == [(2, "f2")]
    assert flow.dropped == ["f0"]


def test_ack_followed_by_refusal_counts_as_refused() -> None:
    flow = FlowControl(window=2, max_pending=8)
    flow.on_sent(0, "f0")
    flow.on_ack(0, 8)
    flow.on_refused(0)
    assert flow.recovery_ready()
    assert flow.take_resends()[0] == [(0, "f0")]
    assert flow.unsettled == 0


def test_giving_up_after_too_many_rounds_without_progress() -> None:
    flow = FlowControl(window=4, max_pending=8, max_retries=2, backoff_s=0.01)
    delays = []
    for _ in range(2):  # a whole window refused per round counts as one round
        for seq in range(4):
            flow.on_sent(seq, f"f{seq}")
            flow.on_refused(seq)
        delays.append(flow.take_resends()[1])
    assert delays == pytest.approx([0.01, 0.02])
    flow.on_sent(0, "f0")
    flow.on_refused(0)
    with pytest.raises(BackpressureError, match="3 times in a row"):
        flow.take_resends()


def test_an_accepted_frame_resets_the_rounds() -> None:
    flow = FlowControl(window=2, max_pending=8, max_retries=1)
    for _ in range(3):
        flow.on_sent(0, "f0")
        flow.on_refused(0)
        flow.take_resends()
        flow.on_sent(0, "f0")
        flow.on_ack(0, 1)
    assert flow.refusal_rounds == 0


def test_rejected_frames_are_settled_without_retry() -> None:
    flow = FlowControl(window=1, max_pending=4)
    flow.on_sent(0, "corrupt")
    flow.on_rejected(0)
    assert flow.unsettled == 0 and not flow.recovery_ready() and flow.can_send()


def test_invalid_settings_are_rejected() -> None:
    with pytest.raises(ValueError):
        FlowControl(window=0)
    with pytest.raises(ValueError):
        FlowControl(max_retries=-1)


def test_after_a_refusal_round_one_frame_probes_until_one_is_accepted() -> None:
    flow = FlowControl(window=4, max_pending=8)
    for seq in range(3):
        flow.on_sent(seq, f"f{seq}")
        flow.on_refused(seq)
    resend, _ = flow.take_resends()
    flow.on_sent(*resend[0])
    assert not flow.can_send()  # the window is 4, but only the probe goes out
    flow.on_ack(0, 4)
    assert flow.can_send()
