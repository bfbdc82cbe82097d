"""A 5-axis program on real grblHAL at time scale 1, every line `ok` (issue 38 item 5).

    .venv/bin/python -m bench.grblhal5 [--part tube|frustum] [--passes 1]

The program is what the CNC executor streams for the first passes of a 5-axis part planned on the
A/B table (bench/five_axis.py's tube or frustum): per pass the approach (G94, rapids with A and B),
`M3`, the G93 inverse-time weld lines of the chord-tolerance fit, `M5`, G94. grblHAL's Simulator
(built once by tests/peers/firmware.py from the peers' sources, 5 axes, set up as a fast machine)
runs it at real time through CncLink's character counting. The figures: lines sent, lines
answered `ok`, the firmware's axis count from its status report, the wall time, and the shortest
line's time against twice its serial time at 115200 baud.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.five_axis import kin_cfg, plan5  # noqa: E402
from bench.parts5 import cone_frustum, tilted_tube  # noqa: E402
from controller.job.read import job_from_dict  # noqa: E402
from controller.motion.cnc5 import Five  # noqa: E402
from controller.motion.kinematics import Trunnion  # noqa: E402
from tests.peers import firmware  # noqa: E402

BAUD = 115200


async def program(part: str, passes: int) -> list[str]:
    """The executor's lines for the first `passes` passes of the part (A/B table)."""
    job = job_from_dict(plan5(tilted_tube() if part == "tube" else cone_frustum()))
    five = Five(Trunnion.from_config(kin_cfg("AB").kinematics))
    await five.post_job(job, 2.0, BAUD)
    lines: list[str] = []
    todo = [(li, pi, p) for li, la in enumerate(job.layers) for pi, p in enumerate(la.passes)][:passes]
    for li, pi, p in todo:
        five.use(li, pi)
        first = (float(p.points[0][0]), float(p.points[0][1]), float(p.points[0][2]))
        lines += five.approach_lines(first, 5.0, 3000.0) + ["M3 S1000"] + five.weld_lines(0, p.speeds()) + ["M5"]
    return lines


def shortest_line(lines: list[str]) -> dict:
    """The G93 weld line of least time against twice its serial time (10 bits a byte at BAUD)."""
    worst = None
    for ln in lines:
        if ln.startswith("G1") and " F" in ln and " A" in ln:
            t, serial = 60.0 / float(ln.rsplit("F", 1)[1]), (len(ln) + 1) * 10.0 / BAUD
            if worst is None or t / serial < worst[0]:
                worst = (t / serial, t)
    return {"shortest_line_ms": round(worst[1] * 1000, 2), "shortest_over_serial": round(worst[0], 2)} if worst else {}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="bench.grblhal5")
    ap.add_argument("--part", choices=("tube", "frustum"), default="tube")
    ap.add_argument("--passes", type=int, default=1)
    a = ap.parse_args(argv)
    firmware.build("grblhal")
    lines = asyncio.run(program(a.part, a.passes))
    t0 = time.monotonic()
    out, axes = asyncio.run(firmware.stream_program("grblhal", lines, fast=True))
    print(json.dumps({"part": a.part, "passes": a.passes, "lines": len(lines), "sent": out.lines,
                      "ok": out.acked, "every_line_ok": out.acked == out.lines == len(lines), "axes": axes,
                      "wall_s": round(time.monotonic() - t0, 1), **shortest_line(lines)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
