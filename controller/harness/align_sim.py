"""`cell align run --sim`: the alignment routine on a cell opened with its CNC simulator alone;
`_with_sim`: the CNC simulator served in this loop, for rigs that drive its link directly."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Awaitable, Callable, TypeVar

from controller.align.routine import AlignResult, ProbePlan
from controller.api import align_at
from controller.harness.cell import open_cell
from core.config import CellConfig, SimConfig
from sims import cnc
from sims.clock import SimClock
from sims.up import SimContext
from sims.world import World

T = TypeVar("T")
CNC_MODULE = "sims.cnc"   # the CNC's simulator (sims/up.py SIM_MODULES)


async def _with_sim(cell: CellConfig, sim_cfg: SimConfig, config_dir: Path | None,
                    body: Callable[[str, object], Awaitable[T]]) -> T:
    """Serve the CNC simulator in this loop on an ephemeral loopback port and run body(url, sim)."""
    ctx = SimContext(cell=cell, sim=sim_cfg, world=World(None), clock=SimClock(cell.cell.time_scale),
                     ephemeral=True, faults=sim_cfg.faults, config_dir=config_dir)
    served = await cnc.serve(ctx)
    try:
        return await body(served[0].url, served[0].sim)
    finally:
        for sv in served:
            await sv.close()
        ctx.world.close()


async def run_with_sim(cell: CellConfig, sim_cfg: SimConfig, plan: ProbePlan, *, config_dir: Path | None = None,
                       settings: Any = None, no_level: bool = False) -> AlignResult:
    """The alignment routine on a cell opened with its CNC simulator alone (controller/harness/cell.py)."""
    async with open_cell(cell, sim=sim_cfg, faults=sim_cfg.faults, modules=[CNC_MODULE], config_dir=config_dir,
                         connect=False) as ctl:
        return await align_at(ctl.cfg.devices.cnc.url, ctl.cfg, plan, settings=settings, no_level=no_level)
