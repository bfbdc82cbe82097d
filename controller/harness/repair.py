"""`cell repair run --sim` and `cell demo --repair`: the repair chain against in-process simulators."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

from controller.harness.sim import SIM_REPLY_TIMEOUT_MS, SimHarness, simulated
from controller.job.model import CellJob
from controller.motion.cnc5 import limit_time_scale
from controller.repair import repair_run
from core.config import CellConfig, SimConfig


async def repair_run_sim(job: CellJob, cell: CellConfig, sim_cfg: SimConfig, *, job_path: Path | None = None,
                         runs_dir: str | Path = "runs", log_dir: str | Path | None = None,
                         tolerance_mm: float = 0.1, finish: bool = True,
                         inspect: Callable[[SimHarness, dict[str, Any]], None] | None = None,
                         on_phase: Callable[[SimHarness, str], None] | None = None) -> dict[str, Any]:
    """repair_run against the simulators (the stock posed by `sim_cfg`), logs in `log_dir`;
    `inspect(harness, report)` before the simulators stop (benches read the simulated world);
    `on_phase(harness, name)` as each phase begins (the machine idle)."""
    if cell.cell.platform != "cnc":
        cell = cell.model_copy(update={"cell": cell.cell.model_copy(update={"platform": "cnc"})})
    probing = cell.cell.time_scale
    cell, note = limit_time_scale(cell, job)  # what the CNC link can feed (issue 29)
    with simulated(cell, sim_cfg, log_dir=log_dir) as (cfg, harness):
        # the limit is the build's (its weld moves streamed one line each); the probe cycles send a
        # few lines per touch and run at the cell's own time scale, the machine idle at each switch
        def phase(name: str) -> None:
            harness.clock.set_scale(cell.cell.time_scale if name == "build" else probing)
            if on_phase is not None:
                on_phase(harness, name)

        rep = await repair_run(job, cfg, job_path=job_path, runs_dir=runs_dir,
                               reply_timeout_ms=SIM_REPLY_TIMEOUT_MS, tolerance_mm=tolerance_mm, phase=phase,
                               finish=finish, time_scale_of=lambda name: probing)
        if inspect is not None:
            inspect(harness, rep)
    rep["time_scale"] = cell.cell.time_scale
    rep["time_scale_probing"] = probing
    if note:
        rep.setdefault("notes", []).append(note)
    return rep
