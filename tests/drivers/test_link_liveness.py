"""The shared link-liveness base (drivers/liveness.py) and the RLP/1 window bookkeeping
(drivers/rlp_window.py), without a device: heard / late / bad / lost, and tickets."""
from __future__ import annotations

from collections import deque

import pytest

from drivers.liveness import LinkHealth, LinkLiveness
from drivers.rlp_window import RtoEstimator, TicketWindow
from drivers.robot_records import Ack, Exe, Sta, decode_reply
from wire import rlp


class Link(LinkLiveness[LinkHealth]):
    def __init__(self) -> None:
        super().__init__(LinkHealth(), lost_after_s=3.0, late_after_s=0.75)


def test_heard_late_bad_and_lost_are_counted_by_time_since_the_last_valid_reply():
    link = Link()
    link._link_up(100.0)
    assert not link._heard(100.5) and link.stats.heard == 1 and link.stats.late == 0
    assert not link._quiet(101.0) and link._quiet(101.3)
    assert link._heard(101.3) and link.stats.late == 1           # late: counted, not lost
    assert [link._bad() for _ in range(3)] == [1, 2, 3] and link.stats.bad == 3
    link._valid()
    assert link._bad() == 1                                        # a valid frame ends the run
    assert not link._lost_due(104.0) and link._lost_due(104.3)
    assert link._lost_due(104.29, margin_s=0.02)
    link._allow_silence_until(110.0)                               # e.g. a silent homing cycle
    assert not link._lost_due(109.0) and link._lost_due(110.0)
    link._count_lost()
    assert link.stats.as_dict()["lost"] == 1


def test_late_after_must_lie_within_lost_after():
    with pytest.raises(ValueError, match="late_after_s"):
        LinkLiveness(LinkHealth(), lost_after_s=1.0, late_after_s=2.0)


def test_window_acks_executes_and_resyncs_across_the_16_bit_wrap():
    w = TicketWindow(RtoEstimator(0.1, 1.0, deque()))
    assert w.resync(Sta("IDLE", 0xFFF0, 0xFFF0, 8, (0.0, 0.0, 0.0)), resume_ticket=0xFFF0) is None
    tickets = [w.queue(rlp.encode_move(w.next_ticket, "MARK", n)) for n in range(10)]
    assert tickets == list(range(0xFFF1, 0xFFF1 + 10))
    sent = [w.take_next(None, 1.0) for _ in range(10)]
    assert [s[0] for s in sent if s] == tickets[:8]                # the robot's queue holds 8
    w.on_ack(Ack(0xFFF8, 0), 1.01)
    assert w.last_ack == 0xFFF8 and w.rtt.srtt == pytest.approx(0.01)
    assert list(w.executed(0xFFF3)) == [0xFFF1, 0xFFF2, 0xFFF3] and w.has_room()
    assert w.implausible(Exe(0x0005), frames_lost=False, paused=False) is not None   # never sent
    assert w.implausible(Ack(0xFFF8, 0), frames_lost=False, paused=False) is None
    assert list(w.on_sta(Sta("RUN", 0xFFF8, 0xFFF8, 8, (0.0, 0.0, 0.0)), 1.1)) == list(range(0xFFF4, 0xFFF9))
    st = w.after_reset(Sta("IDLE", 0, 0, 8, (0.0, 0.0, 0.0)))
    assert st.last_exec_ticket == 0x10000 and w.next_ticket == 0x10001


def test_replies_decode_into_one_typed_record_per_kind():
    assert decode_reply(rlp.encode("ACK 002A 7")) == Ack(0x2A, 7)
    assert decode_reply(rlp.encode(rlp.sta("RUN", 3, 2, 60, (1.0, 2.0, 3.0)))) == Sta("RUN", 3, 2, 60, (1.0, 2.0, 3.0))
    with pytest.raises(rlp.FrameError) as e:
        decode_reply(b"ACK 002A 7 *00000000\n")
    assert e.value.reason == "CRC"
