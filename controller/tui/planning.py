"""Planning and probing helpers of the TUI session: the alignment routine's touches, the planner child."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from core.config import load_material, load_sim


def probe_plan(cfg: Any, sim_cfg: Any = None) -> tuple[tuple[str, tuple[float, float, float]], ...]:
    """The touches of the alignment routine's plan, as (face, CAD point), for the Align screen.

    The plan is the routine's own (`plan_for_mesh` on the nominal part of the sim config's
    workpiece); nothing on a robot cell, or when the routine is not there.
    """
    try:
        # lazy: the controller's API loads when the Align screen first needs the plan
        from controller.api import workpiece_probe_plan

        plan = workpiece_probe_plan(sim_cfg or load_sim())
    except Exception:  # no routine, no workpiece: the screen says the plan is the routine's
        return ()
    out = [("top", (float(x), float(y), plan.top_z)) for x, y in plan.top_xy]
    out += [("side", (plan.side_x, float(y), plan.side_z)) for y in plan.side_y]
    out.append(("tertiary", (plan.tertiary_xy[0], plan.tertiary_xy[1], plan.side_z)))
    return tuple(out)


def plan_main(argv: list[str]) -> int:
    """Child process of `CellSession.plan`: PATH WIDTH MATERIAL OUT.

    Prints `progress i n` lines, writes the job JSON to OUT, or prints `error <message>`.
    """

    path, width, material, out = argv
    try:
        # lazy: the planner (shapely, trimesh) loads only when a part is planned
        from planner.job import job_to_dict
        from planner.plan import PlanOptions, plan_part

        def progress(i: int, n: int) -> None:
            print(f"progress {i} {n}", flush=True)

        job = plan_part(path, PlanOptions(width_mm=float(width)), load_material(material), progress=progress)
        Path(out).write_text(json.dumps(job_to_dict(job)), encoding="utf-8")
        print("done", flush=True)
        return 0
    except Exception as exc:  # the message goes to the operator
        print("error " + (str(exc) or exc.__class__.__name__).replace("\n", " "), flush=True)
        sys.stdout.flush()
        return 2


if __name__ == "__main__":
    import sys

    raise SystemExit(plan_main(sys.argv[2:]))
