"""Contract tests of the robot link: RobotLink against the robot simulator, over real bytes.

Each test serves the simulator on an ephemeral loopback TCP port (or a pty) behind the fault
channel at 115200 baud and drives it through drivers.robot.RobotLink. The simulator's
execution log (robot.jsonl) is the ground truth: every planned move ran exactly once, in order.
"""
from __future__ import annotations

import asyncio
import json
import time

import pytest

from wire import rlp
from drivers.errors import DeviceError, LinkLost
from drivers.robot import RobotLink
from sims.world import World
from tests.drivers.robot_cell import Cell, plan, run_moves, assert_exactly_once

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


async def test_clean_link_executes_plan_once_in_order(tmp_path):
    moves = plan(300)
    async with Cell(tmp_path) as cell:
        link = RobotLink(cell.url)
        st = await link.connect()
        assert (st.state, st.last_rx, st.last_exec, st.queue_free) == ("IDLE", 0, 0, 64)
        exe: list[int] = []

        async def collect():
            async for ev in link.events():
                if ev.kind == "EXE":
                    exe.append(ev.ticket)

        task = asyncio.create_task(collect())
        await asyncio.sleep(0)
        tickets = await run_moves(link, moves)
        task.cancel()
        assert tickets == list(range(1, 301))
        assert exe == tickets  # one EXE event per move, in order
        assert link.last_exec_ticket == 300 and link.last_ack_ticket == 300
        assert link.stats.resends == 0 and link.stats.naks == 0
        assert link.stats.frames_sent >= 300 and link.stats.rtt_ms_mean > 0
        await link.close()
    assert_exactly_once(cell.executed(), moves)


async def test_noisy_link_loses_nothing_and_repeats_nothing(tmp_path):
    moves = plan(250)
    async with Cell(tmp_path, spec="seed=11,corrupt=0.005,drop=0.001,latency=1ms") as cell:
        link = RobotLink(cell.url)
        await link.connect()
        await run_moves(link, moves)
        assert link.stats.resends > 0 and link.stats.naks > 0
        assert cell.sim.crc_errors > 0 and cell.sim.duplicates >= 0
        await link.close()
    assert_exactly_once(cell.executed(), moves)


async def test_hold_is_acknowledged_with_a_full_queue_and_go_resumes(tmp_path):
    async with Cell(tmp_path, time_scale=1.0) as cell:  # 1 mm at 60 mm/min: the queue stays full
        link = RobotLink(cell.url)
        await link.connect()
        for i in range(64):
            await link.send_move("MOVL", float(i + 1), 0, 0, 0, 0, 1, 60)
        await link.drain(timeout=10)
        assert cell.sim.state == "RUN" and len(cell.sim.queue) == 64
        t0 = time.monotonic()
        st = await link.hold()
        latency = time.monotonic() - t0
        assert st.state == "HOLD" and latency < 0.25  # strict 20 ms figure: bench/link.py
        x = cell.sim.pos[0]
        await asyncio.sleep(0.3)
        assert cell.sim.pos[0] == x  # motion stopped
        st = await link.go()
        assert st.state == "RUN"
        await asyncio.sleep(0.3)
        assert cell.sim.pos[0] > x
        await link.close()


async def test_silent_link_is_detected_and_the_robot_holds(tmp_path):
    async with Cell(tmp_path, time_scale=1.0) as cell:
        link = RobotLink(cell.url, auto_reconnect=False)
        await link.connect()
        t = None
        for i in range(5):
            t = await link.send_move("MOVL", float(i + 1), 0, 0, 0, 0, 1, 30)
        await link.drain(timeout=5)
        cell.server.stall(6.0)  # the cable goes dead without closing: only silence tells
        t0 = time.monotonic()
        with pytest.raises(LinkLost) as exc:
            await link.wait_executed(t, timeout=20)
        detected = time.monotonic() - t0
        assert 2.5 < detected < 4.5
        assert "robot" in str(exc.value) and cell.url in str(exc.value)
        await asyncio.sleep(0.3)
        assert cell.sim.state == "HOLD" and cell.sim.silence_held
        await link.close()


async def test_unplug_replug_resumes_from_the_robots_sequence_numbers(tmp_path):
    moves = plan(240)
    async with Cell(tmp_path, time_scale=100.0) as cell:
        link = RobotLink(cell.url)
        events = []
        lost = asyncio.Event()

        def on_event(e):
            if e.kind.startswith("link"):
                events.append(e.kind)
            if e.kind == "link_lost":
                lost.set()

        link.on_event(on_event)
        await link.connect()
        sent = 0
        for trial in range(3):
            while sent < 80 * (trial + 1):
                try:
                    await link.send_move(*moves[sent])
                    sent += 1
                except LinkLost:
                    await link.wait_connected(timeout=10)
            lost.clear()
            cell.server.unplug()
            await asyncio.wait_for(lost.wait(), 5)
            await link.wait_connected(timeout=10)
            st = await link.status()
            if st.state == "HOLD":
                await link.go()
            # resynchronised: the next ticket follows what the robot received
            assert link.last_ack_ticket == st.last_rx_ticket or link.last_ack_ticket >= st.last_rx_ticket
        await link.wait_executed(sent, timeout=30)
        assert events.count("link_lost") == 3 and events.count("link_restored") == 3
        await link.close()
    assert_exactly_once(cell.executed(), moves)


async def test_a_new_driver_resumes_across_the_16_bit_wrap(tmp_path):
    async with Cell(tmp_path) as cell:
        cell.sim.last_rx = cell.sim.last_exec = 0xFFF0  # the robot has run 65520 frames of this job
        link = RobotLink(cell.url)
        st = await link.connect(resume_ticket=0xFFF0)
        assert st.last_exec_ticket == 0xFFF0
        moves = plan(40)
        tickets = await run_moves(link, moves)
        assert tickets[0] == 0xFFF1 and tickets[-1] == 0xFFF0 + 40 and link.last_exec_ticket == 0xFFF0 + 40
        await link.close()
        # a second host process resumes with its journaled ticket: numbering continues past 65535
        link2 = RobotLink(cell.url)
        st = await link2.connect(resume_ticket=tickets[-1])
        assert st.last_rx_ticket == 0xFFF0 + 40
        t = await link2.send_move("MOVL", 0, 0, 0, 0, 0, 1, 1500)
        assert t == 0xFFF0 + 41
        await link2.wait_executed(t, timeout=10)
        await link2.close()
    assert_exactly_once(cell.executed(), moves + [("MOVL", 0.0, 0.0, 0.0)], first_seq=0xFFF1)


async def test_wait_mark_abort_fault_and_reset(tmp_path):
    async with Cell(tmp_path, time_scale=50.0) as cell:
        link = RobotLink(cell.url)
        marks = []
        link.on_event(lambda e: marks.append(e.value) if e.kind == "MRK" else None)
        await link.connect()
        await link.send_move("MOVL", 5, 0, 0, 0, 0, 1, 3000)
        await link.send_move("MARK", 7)
        w = await link.send_move("WAIT")
        after = await link.send_move("MOVL", 6, 0, 0, 0, 0, 1, 3000)
        await asyncio.sleep(0.5)
        assert marks == [7] and cell.sim.state == "WAIT" and link.last_exec_ticket == w - 1
        await link.go()
        await link.wait_executed(after, timeout=5)
        # abort flushes what is queued: those moves never run, their waiters are told
        await link.hold()
        queued = [await link.send_move("MOVL", 10 + i, 0, 0, 0, 0, 1, 60) for i in range(5)]
        await link.drain(timeout=5)
        st = await link.abort()
        assert st.queue_free == 64 and st.state == "IDLE"
        with pytest.raises(DeviceError, match="flushed"):
            await link.wait_executed(queued[-1], timeout=2)
        # a move outside the workspace faults the robot; reset clears it and restarts at seq 0001
        bad = await link.send_move("MOVL", 900, 0, 0, 0, 0, 1, 3000)
        with pytest.raises(DeviceError, match="outside workspace"):
            await link.wait_executed(bad, timeout=5)
        assert cell.sim.state == "FAULT"
        st = await link.reset()
        assert (st.state, st.last_rx, st.last_exec) == ("IDLE", 0, 0)
        t = await link.send_move("MOVL", 1, 1, 1, 0, 0, 1, 3000)
        assert t & 0xFFFF == 1 and t > bad
        await link.wait_executed(t, timeout=5)
        await link.close()
    log = cell.executed()
    assert [e["verb"] for e in log] == ["MOVL", "MARK", "WAIT", "MOVL", "MOVL"]
    assert log[-1]["seq"] == 1 and all(e["target"][0] < 10 for e in log)


async def test_robot_reports_torch_motion_to_the_world(tmp_path):
    world = World(tmp_path)
    world.set_arc(True, 120.0, 20.0, 0.0)
    async with Cell(tmp_path, world=world, time_scale=100.0) as cell:
        link = RobotLink(cell.url)
        await link.connect()
        await run_moves(link, [("MOVL", 10, 0, 0, 0, 0, 1, 1500), ("MOVL", 10, 5, 0, 0, 0, 1, 1500)])
        await link.close()
    world.close()
    segs = [json.loads(x) for x in (tmp_path / "deposit.jsonl").read_text().splitlines()]
    assert [(s["from"], s["to"]) for s in segs] == [([0, 0, 0], [10, 0, 0]), ([10, 0, 0], [10, 5, 0])]
    # 10 mm at 1500 mm/min take 0.4 s of simulated time
    assert segs[0]["t1"] - segs[0]["t0"] == pytest.approx(0.4, abs=1e-6)


async def test_link_over_a_pty(tmp_path):
    moves = plan(40)
    async with Cell(tmp_path, pty=True) as cell:
        assert cell.url.startswith("/dev/")
        link = RobotLink(cell.url)
        await link.connect()
        await run_moves(link, moves)
        await link.close()
    assert_exactly_once(cell.executed(), moves)


async def test_duplicates_are_acked_but_never_executed_twice(tmp_path):
    """Speak raw bytes to the simulator: resend a frame, skip one, corrupt one."""
    async with Cell(tmp_path) as cell:
        out: list[bytes] = []
        cell.sim.attach(out.append)
        f1 = rlp.encode_move(1, "MOVL", 1, 0, 0, 0, 0, 1, 3000)
        f3 = rlp.encode_move(3, "MOVL", 3, 0, 0, 0, 0, 1, 3000)
        cell.sim.feed(f1 + f1)
        cell.sim.feed(f3)
        bad = bytearray(rlp.encode_move(2, "MOVL", 2, 0, 0, 0, 0, 1, 3000))
        bad[8] ^= 0x04
        cell.sim.feed(bytes(bad))
        cell.sim.feed(rlp.encode_move(2, "MOVL", 2, 0, 0, 0, 0, 1, 3000))
        replies = [rlp.decode(b) for chunk in out for b in chunk.splitlines()]
        assert replies[:4] == ["ACK 0001 63", "NAK 0002 SEQ", "NAK 0002 CRC", "ACK 0002 62"]
        await asyncio.sleep(0.3)
    assert [e["seq"] for e in cell.executed()] == [1, 2]


async def test_a_robot_that_forgot_acknowledged_moves_is_reported(tmp_path):
    async with Cell(tmp_path, time_scale=1.0) as cell:
        link = RobotLink(cell.url)
        restored = asyncio.Event()
        texts = []
        link.on_event(lambda e: (texts.append(e.text), restored.set()) if e.kind == "link_restored" else None)
        await link.connect()
        tickets = [await link.send_move("MOVL", float(i + 1), 0, 0, 0, 0, 1, 60) for i in range(10)]
        await link.drain(timeout=5)
        # the robot controller reboots while the cable is out: its queue and numbers are gone
        cell.sim.queue.clear()
        cell.sim.last_rx = cell.sim.last_exec = 0
        cell.server.unplug()
        await asyncio.wait_for(restored.wait(), 10)
        assert "lost queued moves" in texts[0]
        with pytest.raises(DeviceError, match="lost queued moves"):
            await link.wait_executed(tickets[-1], timeout=5)
        await link.close()


async def test_serial_adapter_on_loop_url_and_a_silent_device():
    from drivers.serial_async import SerialPort

    port = SerialPort("loop://", baud=115200)
    await port.open()
    t0 = time.monotonic()
    await port.write(b"x" * 576)   # 50 ms of line time at 115200 8N1
    await port.write(b"!")
    assert time.monotonic() - t0 > 0.04  # paced like a UART
    got = b""
    while len(got) < 577:
        got += await asyncio.wait_for(port.read(), 2)
    assert got == b"x" * 576 + b"!"
    port.close()
    # loop:// only echoes the host's own frames: nobody answers !STATUS
    link = RobotLink("loop://", link_timeout_s=0.5, auto_reconnect=False)
    with pytest.raises(LinkLost, match="no answer to !STATUS"):
        await link.connect()
    with pytest.raises(LinkLost, match="cannot open"):
        await RobotLink("socket://127.0.0.1:1", auto_reconnect=False).connect()


async def test_unplug_from_the_fault_spec_keeps_the_cable_out_then_resumes(tmp_path):
    moves = plan(60)
    async with Cell(tmp_path, spec="seed=2,unplug@t=0.6s,unplug=0.8s", time_scale=1.0) as cell:
        link = RobotLink(cell.url)
        times = {}
        link.on_event(lambda e: times.setdefault(e.kind, time.monotonic()))
        await link.connect()
        sent = 0
        while sent < len(moves):
            try:
                await link.send_move(*moves[sent])
                sent += 1
            except LinkLost:
                await link.wait_connected(timeout=10)
        while True:  # the cable is pulled while the robot works through its queue
            try:
                await link.wait_executed(len(moves), timeout=30)
                break
            except LinkLost:
                await link.wait_connected(timeout=10)
        assert times["link_restored"] - times["link_lost"] >= 0.7  # refused while unplugged
        await link.close()
    assert_exactly_once(cell.executed(), moves)
