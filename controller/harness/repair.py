"""`cell repair run` and `cell demo --repair`: the repair chain (controller/repair.py) on a cell
opened here (controller/harness/cell.py): its devices, or the in-process simulators."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

from controller.api.simulated import Simulators
from controller.harness.cell import open_cell
from controller.defaults import SIM_REPLY_TIMEOUT_MS
from controller.harness.sim_clock import FedScale
from controller.job.model import CellJob
from controller.motion.cnc5 import limit_time_scale
from controller.repair import repair_cell, repair_run
from core.config import CellConfig, SimConfig


async def repair_run_devices(job: CellJob, cell: CellConfig, *, job_path: Path | None = None,
                             runs_dir: str | Path = "runs", tolerance_mm: float = 0.1,
                             finish: bool = True, say: Callable[[str], None] | None = None) -> dict[str, Any]:
    """repair_run on the devices of cell.yaml (hardware, or `cell sim up`): where the host cannot
    feed the build at the cell's time scale, the simulators' clock is lowered for the build and
    given back for the probing (docs/controller.md, "Simulated time the host can feed"); refused
    before any device when no clock answers."""
    cell = repair_cell(cell)
    probing = cell.cell.time_scale
    fed = FedScale.lower(cell, job)
    if fed.note and say is not None:
        say(fed.note)
    built_at = fed.cfg.cell.time_scale

    def phase(name: str) -> None:
        fed.set(built_at if name == "build" else probing)

    try:
        async with open_cell(fed.cfg, runs_dir=runs_dir, connect=False) as ctl:
            rep = await repair_run(ctl, job, job_path=job_path, tolerance_mm=tolerance_mm, finish=finish,
                                   phase=phase, time_scale_of=lambda name: probing)
    finally:
        fed.restore()
    if fed.note:
        rep["time_scale"] = built_at
        rep["time_scale_probing"] = probing
        rep.setdefault("notes", []).append(fed.note)
    return rep


async def repair_run_sim(job: CellJob, cell: CellConfig, sim_cfg: SimConfig, *, job_path: Path | None = None,
                         runs_dir: str | Path = "runs", log_dir: str | Path | None = None,
                         tolerance_mm: float = 0.1, finish: bool = True,
                         inspect: Callable[[Simulators, dict[str, Any]], None] | None = None,
                         on_phase: Callable[[Simulators, str], None] | None = None) -> dict[str, Any]:
    """repair_run against the simulators (the stock posed by `sim_cfg`), logs in `log_dir`;
    `inspect(simulators, report)` before the simulators stop (benches read the simulated world);
    `on_phase(simulators, name)` as each phase begins (the machine idle)."""
    cell = repair_cell(cell)
    probing = cell.cell.time_scale
    cell, note = limit_time_scale(cell, job)  # what the CNC link can feed (issue 29)
    async with open_cell(cell, sim=sim_cfg, log_dir=log_dir, runs_dir=runs_dir, connect=False,
                         reply_timeout_ms=SIM_REPLY_TIMEOUT_MS) as ctl:
        sims = ctl.simulators
        assert sims is not None

        # the limit is the build's (its weld moves streamed one line each); the probe cycles send a
        # few lines per touch and run at the cell's own time scale, the machine idle at each switch
        def phase(name: str) -> None:
            sims.set_time_scale(cell.cell.time_scale if name == "build" else probing)
            if on_phase is not None:
                on_phase(sims, name)

        rep = await repair_run(ctl, job, job_path=job_path, tolerance_mm=tolerance_mm, phase=phase,
                               finish=finish, time_scale_of=lambda name: probing)
        if inspect is not None:
            inspect(sims, rep)
    rep["time_scale"] = cell.cell.time_scale
    rep["time_scale_probing"] = probing
    if note:
        rep.setdefault("notes", []).append(note)
    return rep

