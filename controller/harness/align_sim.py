"""`cell align run --sim`: the alignment routine on a cell opened with its CNC simulator alone
(`open_cell(..., modules=[CNC_MODULE])`, as the rigs that drive the CNC's link directly open it)."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

from controller.align.probe_cycle import ProbedPoint
from controller.align.routine import AlignResult, ProbePlan
from controller.api import align_at
from controller.harness.cell import open_cell
from core.config import CellConfig, ProbeSettings, SimConfig

CNC_MODULE = "sims.cnc"   # the CNC's simulator (sims/up.py SIM_MODULES)


async def run_with_sim(cell: CellConfig, sim_cfg: SimConfig, plan: ProbePlan, *, config_dir: Path | None = None,
                       settings: ProbeSettings | None = None, no_level: bool = False,
                       on_point: Callable[[ProbedPoint], None] | None = None) -> AlignResult:
    """The alignment routine on a cell opened with its CNC simulator alone (controller/harness/cell.py)."""
    async with open_cell(cell, sim=sim_cfg, faults=sim_cfg.faults, modules=[CNC_MODULE], config_dir=config_dir,
                         connect=False) as ctl:
        return await align_at(ctl.cfg.devices.cnc.url, ctl.cfg, plan, settings=settings, no_level=no_level,
                              on_point=on_point)
