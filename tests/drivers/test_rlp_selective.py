"""RLP/2, selective repeat on the robot link (docs/protocols/rlp.md §9): negotiated at connect,
RLP/1 still spoken by both ends, only lost frames sent again, an adaptive retransmit timeout.

The real-socket tests run RobotLink against the robot simulator behind the fault channel (the
simulator's robot.jsonl is the judge); the fuzz runs the host's window against the simulator's
receiver over bench/rlp_fuzz.py's virtual line (virtual time, reproducible from its seed).
"""
from __future__ import annotations


import asyncio

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.rlp_fuzz import run as fuzz_run
from drivers.robot import RobotLink
from tests.drivers.robot_cell import Cell, assert_exactly_once, plan, run_moves
from wire import rlp

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


@pytest.mark.parametrize(("host", "robot", "spoken"), [(2, 2, 2), (2, 1, 1), (1, 2, 1)],
                         ids=["both-rlp2", "rlp1-robot", "rlp1-host"])
async def test_the_protocol_is_negotiated_and_rlp1_is_still_spoken(tmp_path, host, robot, spoken):
    moves = plan(150)
    async with Cell(tmp_path, spec="seed=5,corrupt=0.01,drop=0.001", max_protocol=robot) as cell:
        link = RobotLink(cell.url, max_protocol=host)
        await link.connect()
        assert link.protocol == spoken and cell.sim.proto == spoken
        assert link.stats.as_dict()["protocol"] == spoken
        await run_moves(link, moves)
        if spoken == 2:
            assert link.stats.sacks > 0              # gaps were reported, and filled alone
            assert link.rto_s >= 0.025
        else:
            assert link.stats.sacks == 0             # an RLP/1 peer never sees a SACK
            assert link.rto_s >= 0.1                 # RLP/1's own bounds
        await link.close()
    assert_exactly_once(cell.executed(), moves)


async def test_the_robot_keeps_frames_beyond_a_gap_and_says_so(tmp_path):
    """Raw bytes to the simulator: ask for RLP/2, then skip a frame, repeat one, fill the gap."""
    async with Cell(tmp_path) as cell:
        out: list[bytes] = []
        cell.sim.attach(out.append)
        f = {n: rlp.encode_move(n, "MOVL", n, 0, 0, 0, 0, 1, 3000) for n in range(1, 6)}
        for chunk in (rlp.encode("!PROTO 2"), f[1], f[3], f[5], f[3], f[2], f[4]):
            cell.sim.feed(chunk)
        replies = [rlp.decode(b) for chunk in out for b in chunk.splitlines()]
        # SACK a credits mask: bit i = frame a + 2 + i is held (frame a + 1 is the gap)
        assert replies == ["PROTO 2", "ACK 0001 63", "SACK 0001 63 1", "SACK 0001 63 5", "SACK 0001 63 5",
                           "SACK 0003 61 1", "ACK 0005 59"]
        assert cell.sim.duplicates == 1
        await asyncio.sleep(0.3)
    assert [e["seq"] for e in cell.executed()] == [1, 2, 3, 4, 5]   # in order, once each


async def test_an_rlp1_robot_refuses_the_question_as_any_unknown_frame(tmp_path):
    async with Cell(tmp_path, max_protocol=1) as cell:
        out: list[bytes] = []
        cell.sim.attach(out.append)
        cell.sim.feed(rlp.encode("!PROTO 2"))
        assert [rlp.decode(b) for chunk in out for b in chunk.splitlines()] == ["NAK 0001 SYNTAX"]


async def test_the_retransmit_timeout_follows_the_measured_round_trip(tmp_path):
    rto = {}
    for latency in ("1ms", "100ms"):   # one way: round trips of a few ms and of 200 ms or more
        async with Cell(tmp_path, spec=f"latency={latency}") as cell:
            link = RobotLink(cell.url)
            await link.connect()
            await run_moves(link, plan(60))
            rto[latency] = link.rto_s
            assert min(link.stats.rtt_s) < link.rto_s           # SRTT + 4 RTTVAR, from measured trips
            assert 0.025 <= link.rto_s <= 5.0                    # RLP/2's bounds
            await link.close()
        assert_exactly_once(cell.executed(), plan(60))
        cell.log.unlink()
    assert rto["100ms"] > 0.2 and rto["100ms"] > rto["1ms"]   # a 200 ms round trip: never under it


def test_selective_repeat_sends_again_only_what_was_lost():
    # the same line, the same noise (1 % of bytes corrupted, 0.1 % dropped), 1,500 moves
    sr = fuzz_run(1500, seed=3, corrupt=0.01, drop=0.001, protocol=2)
    gbn = fuzz_run(1500, seed=3, corrupt=0.01, drop=0.001, protocol=1)
    assert sr.exactly_once_in_order and gbn.exactly_once_in_order
    # a 50-byte frame survives ~57 % of the time: ~0.75 resends per move is the least possible
    assert sr.resends < 0.9 * sr.moves < gbn.resends / 3
    assert sr.robot_duplicates < 0.03 * sr.resends          # frames it had already: rare
    assert sr.fraction_of_line > 0.5 > 0.3 > gbn.fraction_of_line


@settings(max_examples=20, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2 ** 31), corrupt=st.sampled_from([0.0, 1e-3, 1e-2, 3e-2]),
       drop=st.sampled_from([0.0, 1e-4, 1e-3, 1e-2]), protocol=st.sampled_from([1, 2]),
       slots=st.sampled_from([4, 16, 64]))
def test_fuzzed_lines_never_lose_repeat_or_reorder_a_move(seed, corrupt, drop, protocol, slots):
    r = fuzz_run(120, seed=seed, corrupt=corrupt, drop=drop, protocol=protocol, slots=slots)
    assert (r.lost, r.duplicated, r.reordered) == (0, 0, 0)
    assert r.exactly_once_in_order and r.executed == r.moves == 120
