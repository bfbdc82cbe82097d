"""A device that stops in each motion state: the time to the fault, and arc and spindle off (issue 38).

Each stall is a seeded simulator fault on the device's own wire protocol (sims/faults.py), the
in-process simulators of `--sim`:

- robot in travel (`freeze@travel=3`: the first bead's third MOVJ never runs, the robot says RUN),
- robot mid-bead (`freeze@move=20`),
- CNC in Run without moving on its travel (`freeze@travel=3`, a CNC cell),
- a probe move that never ends (`freeze@probe=1`, the alignment's first touch).

For each run: the state the controller named, how long the device stood by the fault's own
account ("made no progress for X s", measured from its last progress), the bound it was held to,
the wall time from the start of the command to the fault, and what the devices say afterwards:
the weld start bit the power source simulator last received (the bus), the robot's `STA` state,
grbl's own status report (state, spindle).

    .venv/bin/python -m bench.stalls --runs 3
"""
from __future__ import annotations

import argparse
import asyncio
import json
import re
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from controller.align.routine import cad_mesh, plan_for_mesh
from controller.api import align_at
from controller.api.simulated import Simulators
from controller.defaults import SIM_REPLY_TIMEOUT_MS
from controller.harness.cell import open_cell, with_urls
from controller.job.read import job_from_dict
from controller.motion.watch import StallFault
from core.config import CellConfig, load_cell, load_sim

SCALE = 5.0


def small_job(z0: float = 0.0) -> dict[str, Any]:
    """Two square beads on one layer (the tests' small job), `z0` above the table."""
    z = 1.0 + z0
    outer = [[0, 0, z], [20, 0, z], [20, 20, z], [0, 20, z], [0, 0.5, z]]
    inner = [[5, 5, z], [15, 5, z], [15, 15, z], [5, 15, z], [5, 5.5, z]]
    bead = {"role": "perimeter", "width_mm": 5, "current_a": 120, "speed_mm_min": 600, "wfs_m_min": 5.5}
    return {"schema": "cell-job/1", "source": {"file": "square.stl", "sha256": "0" * 64, "units": "mm"},
            "material": {"name": "inconel718-1.0mm"},
            "bead": {"width_mm": 5, "height_mm": 1, "step_over_mm": 3.69, "model": "tangent"},
            "layers": [{"index": 0, "z_mm": z, "height_mm": 1.0, "passes": [{**bead, "points": outer},
                                                                           {**bead, "points": inner}]}],
            "summary": {}}


def _stood(msg: str) -> tuple[float | None, float | None]:
    """(seconds stood, the wall bound) from a stall fault's message."""
    stood = re.search(r"made no progress for ([0-9.]+) s", msg)
    bound = re.search(r"progress timeout [0-9.]+ s of process time[^,;)]*?, ([0-9.]+) s wall", msg)
    return (float(stood.group(1)) if stood else None, float(bound.group(1)) if bound else None)


def _power(harness: Simulators) -> tuple[bool, str]:
    sim = harness.sim("power_source")
    return harness.call(lambda: (bool(sim.cmd.bits.get("weld_start")), str(sim.phase)))


async def build_stall(platform: str, faults: str, tmp: Path) -> dict[str, Any]:
    cfg = with_urls(load_cell(), {}, time_scale=SCALE)
    cfg = cfg.model_copy(update={"cell": cfg.cell.model_copy(update={"platform": platform})})
    job = small_job(20.0 if platform == "cnc" else 0.0)   # the CNC's substrate block is 20 mm tall
    out: dict[str, Any] = {}
    async with open_cell(cfg, sim=load_sim(), log_dir=tmp / "log", faults=faults, runs_dir=tmp / "runs",
                         reply_timeout_ms=SIM_REPLY_TIMEOUT_MS) as ctl:
        harness = ctl.simulators
        assert harness is not None
        await asyncio.to_thread(ctl.open_job, job_from_dict(job))
        t0 = time.monotonic()
        res = await asyncio.wait_for(ctl.start(), 60)
        out["wall_to_fault_s"] = round(time.monotonic() - t0, 2)
        await asyncio.sleep(0.3)   # burn-back and post-flow run out at the source
        out["state"] = res.state
        out["message"] = ctl.interlocks.trips[0].message if ctl.interlocks and ctl.interlocks.trips else ""
        out["weld_start_at_source"], out["source_phase"] = _power(harness)
        if platform == "robot" and ctl.devices is not None:
            st = await ctl.devices.robot_link().status()
            out["robot_status"] = st.state
        elif ctl.devices is not None and ctl.devices.cnc is not None:
            rep = await ctl.devices.cnc.status()
            out["cnc_report"] = {"state": rep.state, "spindle": rep.spindle}
    return out


async def probe_stall(tmp: Path) -> dict[str, Any]:
    cell: CellConfig = load_cell()
    cell = cell.model_copy(update={"cell": cell.cell.model_copy(update={"time_scale": 10.0})})
    sim_cfg = load_sim()
    plan = plan_for_mesh(cad_mesh(sim_cfg.cnc.workpiece))
    out: dict[str, Any] = {}
    async with open_cell(cell, sim=sim_cfg, log_dir=tmp / "log", faults="freeze@probe=1", modules=["sims.cnc"],
                         connect=False) as ctl:
        harness = ctl.simulators
        assert harness is not None
        t0 = time.monotonic()
        try:
            await asyncio.wait_for(align_at(ctl.cfg.devices.cnc.url, cell, plan), 60)
            out["state"] = "no fault"
        except StallFault as exc:
            out["state"] = "fault"
            out["message"] = str(exc)
        out["wall_to_fault_s"] = round(time.monotonic() - t0, 2)
        cnc = harness.sim("cnc")
        spindle, state, report = harness.call(lambda: (cnc.machine.spindle_on, cnc.state, cnc.status_line()))
        out["cnc_report"] = {"state": state, "spindle_on": spindle, "status_line": report}
    return out


SCENARIOS = {
    "robot in travel": lambda tmp: build_stall("robot", "freeze@travel=3", tmp),
    "robot mid-bead": lambda tmp: build_stall("robot", "freeze@move=20", tmp),
    "cnc in Run without moving": lambda tmp: build_stall("cnc", "freeze@travel=3", tmp),
    "probe move that never ends": probe_stall,
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("-k", default=None, help="only scenarios whose name contains this")
    a = ap.parse_args(sys.argv[1:] if argv is None else argv)
    rows = []
    for name, fn in SCENARIOS.items():
        if a.k and a.k not in name:
            continue
        for i in range(a.runs):
            with tempfile.TemporaryDirectory(prefix="stall-") as tmp:
                r = asyncio.run(fn(Path(tmp)))
            stood, bound = _stood(r.get("message", ""))
            r.update(scenario=name, run=i, stood_s=stood, bound_wall_s=bound)
            rows.append(r)
            dev = r.get("robot_status") or r.get("cnc_report")
            print(f"{name:28s} #{i}: {r['state']}, stood {stood} s (bound {bound} s wall), "
                  f"{r['wall_to_fault_s']} s from start; weld start at source "
                  f"{r.get('weld_start_at_source', '-')}, device says {dev}", flush=True)
    print(json.dumps({"time_scale": SCALE, "rows": rows}, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
