"""A box built on real grbl 1.1h at time scale 1 with `M4` (issue 35 item 5, docs/laser-power.md).

    .venv/bin/python -m bench.grbl_box [--side 20] [--layers 2] [--speed 600] [--m3] [--keep DIR]

The CNC is grbl 1.1h in grbl-sim (built once by tests/peers/firmware.py, served on a pty through
socat); the power source and the cell I/O are `cell sim up` in their own process, time scale 1.
The job is a square box planned by the planner (feed-forward on: per-segment speeds where it
levels). `cell run` builds it; the figures come from its record (report.json): the state, the
defects, and per bead the stand-stills (`still_count`), the slow-downs the firmware's M4 power
followed (`slowed_count`: null when M4 was not in force) and the measured against planned speed.
`--m3`: the same build at constant power (cell.yaml `devices.cnc.process_power: constant`).
grbl-sim moves at about 0.37x real time, so every bead is slower than planned on the wall clock:
at constant power that reads as stand-stills, under M4 the firmware's own reports show the power
following its speed.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.stops import SimCell, cell  # noqa: E402
from tests.peers import firmware  # noqa: E402

MATERIAL = "inconel718-1.0mm"


def box_job(side: float, layers: int, width: float = 5.0) -> dict:
    """A side × side box, one perimeter a layer, planned (cell-job/2 where the feed-forward levels)."""
    # lazy: the planner only for this job (the bench's start-up)
    import trimesh

    # lazy: the planner only for this job (the bench's start-up)
    from core.config import load_material
    # lazy: the planner only for this job (the bench's start-up)
    from planner.job import job_to_dict
    # lazy: the planner only for this job (the bench's start-up)
    from planner.options import PlanOptions
    # lazy: the planner only for this job (the bench's start-up)
    from planner.plan import plan_part

    h = 0.77
    m = trimesh.creation.box(extents=(side, side, layers * h))
    m.apply_translation((side / 2 + 5.0, side / 2 + 5.0, layers * h / 2.0))
    job = plan_part(m, PlanOptions(width_mm=width, perimeters=1, allow_underfill=True), load_material(MATERIAL))
    return job_to_dict(job)


def run(side: float, layers: int, speed: float | None, m3: bool, work: Path) -> dict:
    jd = box_job(side, layers)
    for la in jd["layers"]:
        for p in la["passes"]:
            if speed is not None and not isinstance(p["speed_mm_min"], list):
                p["speed_mm_min"] = speed
    c = SimCell(work, platform="cnc", time_scale=1.0).up()
    try:
        firmware.build("grbl")
        with firmware.serve("grbl") as pty:
            cfg = json.loads(json.dumps(c.cfg))
            cfg["devices"]["cnc"]["url"] = pty
            cfg["devices"]["cnc"]["process_power"] = "constant" if m3 else "dynamic"
            cfgp = work / "cell-grbl.yaml"
            cfgp.write_text(yaml.safe_dump(cfg))
            jp = work / "box.json"
            jp.write_text(json.dumps(jd))
            t0 = time.monotonic()
            r = cell("run", str(jp), "--cell-config", str(cfgp), "--runs", str(c.runs), "--json",
                     stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            out, err = r.communicate(timeout=1800)
            wall = time.monotonic() - t0
    finally:
        c.down()
    res = json.loads(out.strip().splitlines()[-1]) if out.strip() else {"error": err[-500:]}
    rep = json.loads(Path(res["report"]).read_text()) if res.get("report") else {}
    beads = [{k: b.get(k) for k in ("layer", "pass", "still_count", "still_time_s", "slowed_count",
                                    "speed_planned_mm_min", "speed_measured_mm_min", "arc_time_s", "defect_reasons")}
             for b in rep.get("beads", [])]
    return {"firmware": "grbl 1.1h (grbl-sim)", "time_scale": 1.0, "power": "M3" if m3 else "M4",
            "exit": r.returncode, "state": res.get("state"), "defects": len(res.get("defects") or []),
            "defect_reasons": [d.get("reason") for d in res.get("defects") or []],
            "layers_done": res.get("layers_done"), "passes_done": res.get("passes_done"),
            "m4_in_force": all(b["slowed_count"] is not None for b in beads) and bool(beads),
            "wall_s": round(wall, 1), "beads": beads}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=float, default=20.0)
    ap.add_argument("--layers", type=int, default=2)
    ap.add_argument("--speed", type=float, default=None, help="one speed for every pass the feed-forward left alone")
    ap.add_argument("--m3", action="store_true", help="constant power (for comparison)")
    ap.add_argument("--keep", type=Path, default=None)
    a = ap.parse_args()
    work = a.keep or Path(tempfile.mkdtemp(prefix="grbl-box-"))
    try:
        print(json.dumps(run(a.side, a.layers, a.speed, a.m3, work), indent=1))
    finally:
        if a.keep is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
