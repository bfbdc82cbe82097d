"""Benchmark: stream a 10,000-line G-code program to the CNC simulator with character counting.

Two runs over loopback TCP through the simulated 115200-baud line (sims/transport.py):
1. the whole program: throughput, how full grbl's 127-byte RX ring and 15-block planner stay
   (sampled every 5 ms on the simulator side), bytes lost (must be 0), and that the exec log
   holds every line exactly once in order;
2. its first 2,000 lines with a faulty line at 75 %: the stream stops at the first `error:N`, the error
   names the line, and only what was already in grbl's buffer runs after it.

Usage: python -m bench.cnc_stream [--quick] [--lines N] [--time-scale S]
"""
from __future__ import annotations

import argparse
import asyncio
import json
import math
import statistics
import tempfile
import time
from pathlib import Path

from core.config import Workpiece as WorkpieceConfig
from drivers.grbl import CncLink, GrblError
from sims.clock import SimClock
from sims.cnc import CncSim
from sims.transport import SerialServer
from sims.workpiece import Workpiece
from sims.world import World


def program(n: int) -> list[str]:
    """n lines: units, feed, then a spiral of ~1.5 mm G1 segments 10 mm above the part."""
    lines = ["G21 G90", "G1 F3000"]
    r, a = 5.0, 0.0
    for _ in range(n - 2):
        a += 1.5 / r
        r = min(r + 0.01, 45.0)
        lines.append(f"G1 X{r * math.cos(a):.3f} Y{r * math.sin(a):.3f} Z10")
    return lines


async def _rig(tmp: Path, time_scale: float):
    clock = SimClock(time_scale)
    world = World(tmp)
    sim = CncSim(clock=clock, world=world, workpiece=Workpiece.from_config(WorkpieceConfig(), 0.002),
                 log_path=tmp / "cnc.jsonl")
    sim.start()
    server = SerialServer(sim, name="cnc", baud=115200)
    url = await server.start(None, ephemeral=True)
    link = CncLink(url)
    await link.connect()
    await link.home()
    return sim, server, link


async def _close(sim, server, link) -> None:
    await link.close()
    await server.close()
    await sim.close()


async def run_full(n: int, time_scale: float) -> dict:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        sim, server, link = await _rig(tmp, time_scale)
        prog = program(n)
        rx, planner = [], []
        streaming = True

        async def sample() -> None:
            while streaming:
                rx.append(sim.rx_fill)
                planner.append(sim.machine.motion_in_queue)
                await asyncio.sleep(0.005)

        sampler = asyncio.ensure_future(sample())
        t0 = time.monotonic()
        res = await link.stream(prog)
        wall = time.monotonic() - t0
        streaming = False
        await sampler
        sim.flush_log()
        ran = [json.loads(x)["line"] for x in (tmp / "cnc.jsonl").read_text().splitlines()]
        ran = [x for x in ran if x != "G4P0"]
        once_in_order = ran == [ln.replace(" ", "") for ln in prog]
        # steady state: leave out the first and last 5 % (filling and draining)
        k = len(rx) // 20
        out = {
            "lines": res.lines, "acked": res.acked, "bytes": res.bytes_sent, "wall_s": wall,
            "lines_per_s": res.lines / wall, "bytes_per_s": res.bytes_sent / wall,
            "link_capacity_bytes_per_s": 115200 / 10,
            "driver_mean_in_flight": res.mean_in_flight_bytes, "driver_max_in_flight": res.max_in_flight_bytes,
            "rx_capacity": sim.rx_capacity,
            "sim_rx_fill_mean": statistics.fmean(rx[k:len(rx) - k]) if len(rx) > 2 * k + 1 else float("nan"),
            "sim_planner_fill_mean": statistics.fmean(planner[k:len(planner) - k]) if len(planner) > 2 * k + 1 else float("nan"),
            "planner_blocks": sim.planner_blocks,
            "planner_empty_while_rx_waiting": sim.starved,
            "rx_bytes_lost": sim.rx_dropped,
            "exec_log_every_line_once_in_order": once_in_order,
            "sim_time_s": sim.clock.now(),
        }
        await _close(sim, server, link)
        return out


async def run_error(n: int, bad: int, time_scale: float) -> dict:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        sim, server, link = await _rig(tmp, time_scale)
        prog = program(n)
        prog[bad - 1] = "G1 X1 Y1 W5"
        t0 = time.monotonic()
        try:
            await link.stream(prog)
            err = None
        except GrblError as exc:
            err = exc
        wall = time.monotonic() - t0
        await link.wait_idle(60)
        sim.flush_log()
        ran = [json.loads(x)["line"] for x in (tmp / "cnc.jsonl").read_text().splitlines()]
        ran = [x for x in ran if x != "G4P0"]
        last_good = prog[bad - 2].replace(" ", "")
        after = len(ran) - ran.index(last_good) - 1 if last_good in ran else -1
        out = {
            "error_line_number": err.line_number if err else None, "expected_line_number": bad,
            "error_code": err.code if err else None, "error_text": str(err) if err else "",
            "lines_run_after_error": after, "lines_in_program": n, "wall_s": wall,
        }
        await _close(sim, server, link)
        return out


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="bench.cnc_stream", description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="2,000 lines instead of 10,000")
    ap.add_argument("--lines", type=int, default=None)
    ap.add_argument("--time-scale", type=float, default=10.0,
                    help="process time / wall time (10: the machine, not the line, is the bottleneck)")
    args = ap.parse_args(argv)
    n = args.lines or (2000 if args.quick else 10_000)
    full = asyncio.run(run_full(n, args.time_scale))
    print(f"stream {full['lines']} lines ({full['bytes']} bytes) in {full['wall_s']:.2f} s wall "
          f"({full['sim_time_s']:.0f} s process time at x{args.time_scale:g}): "
          f"{full['lines_per_s']:.0f} lines/s, {full['bytes_per_s']:.0f} B/s "
          f"(line capacity {full['link_capacity_bytes_per_s']:.0f} B/s)")
    print(f"  driver: mean {full['driver_mean_in_flight']:.1f} / {full['rx_capacity']} bytes in flight, "
          f"max {full['driver_max_in_flight']}")
    print(f"  grbl (sim): RX ring mean fill {full['sim_rx_fill_mean']:.1f} / {full['rx_capacity']} bytes, "
          f"planner mean {full['sim_planner_fill_mean']:.1f} / {full['planner_blocks']} blocks, "
          f"planner ran dry with RX waiting {full['planner_empty_while_rx_waiting']}x, "
          f"RX bytes lost {full['rx_bytes_lost']}")
    print(f"  exec log: every line once, in order: {full['exec_log_every_line_once_in_order']}")
    n_err = min(n, 2000)
    bad = max(3, int(n_err * 0.75))
    err = asyncio.run(run_error(n_err, bad, args.time_scale))
    print(f"error run: stopped at line {err['error_line_number']} (expected {bad}), error:{err['error_code']}; "
          f"{err['lines_run_after_error']} lines already in grbl's buffer ran after it; "
          f"{err['wall_s']:.2f} s")
    print(f"  {err['error_text']}")
    ok = (full["acked"] == full["lines"] and full["rx_bytes_lost"] == 0 and full["exec_log_every_line_once_in_order"]
          and err["error_line_number"] == bad)
    return 0 if ok else 1


if __name__ == "__main__":
    import sys

    raise SystemExit(main(sys.argv[1:]))
