"""The alignment routine's touches as the Align screen lists them (planning a part is the API's:
controller/api/planning.py runs the planner in a child process)."""
from __future__ import annotations

from typing import Any

from core.config import load_sim


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
