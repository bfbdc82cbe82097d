"""The controller's API without a cell session: the build record of a run directory, the list of
runs, a run's journal events, an alignment that opens and closes its own CNC link and its probe
plan, a job moved by an alignment (`cell report`, `cell runs`, `cell align run`, the demo's probe,
the TUI's Log and Align screens)."""
from __future__ import annotations

import asyncio
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping

from core.config import CellConfig, ProbeSettings, load_sim
from core.errors import CellError

if TYPE_CHECKING:
    from controller.align.probe_cycle import ProbedPoint
    from controller.align.routine import AlignResult, ProbePlan
    from controller.job.model import CellJob
    from controller.journal.check import Row
    from numpy.typing import ArrayLike
    from core.config import SimConfig


def write_run_report(run_dir: str | Path, *, plots: bool = True, operator: str | None = None,
                     csv_path: str | Path | None = None) -> Path:
    """`cell report RUN_DIR`: the build record of a run directory, from its journal and the job it
    holds (no cell needed); the path of report.json."""
    # lazy: the report modules (matplotlib) load only when a record is written
    from controller.report.run import write_run_report as write

    return write(run_dir, plots=plots, operator=operator, csv_path=csv_path)


def run_rows(runs_dir: str | Path) -> list[dict[str, Any]]:
    """`cell runs`: dir, job, state, started, layers done / total of every run directory."""
    # lazy: the report modules load only when the runs are listed
    from controller.report.run import run_rows as rows

    return rows(Path(runs_dir))


async def align_at(url: str, cell: CellConfig, plan: ProbePlan, *, settings: ProbeSettings | None = None,
                   on_point: Callable[[ProbedPoint], None] | None = None, no_level: bool = False) -> AlignResult:
    """Probe and align on the CNC at `url` outside a build session (the link is opened and closed
    here): `cell align run`, the demo's probe on the CNC and the TUI's Align screen come in here,
    a build session through `CellController.run_alignment`."""
    # lazy: the alignment routine (ICP, trimesh) loads only when a cell is aligned
    from controller.align.routine import run_on_url

    return await run_on_url(url, cell, plan, settings=settings, on_point=on_point, no_level=no_level)


def events_after(run_dir: str | Path, after_id: int = 0, limit: int = 2000) -> list[Row]:
    """A run's journal events with id > after_id: (id, t, kind, state, message, layer, pass), on a
    read-only connection (another thread may read mid-build: the TUI's Log screen)."""
    # lazy: the journal loads only when a run is read
    from controller.journal.store import read_events_after

    return read_events_after(Path(run_dir) / "journal.sqlite", after_id, limit)


def align_off_session(cell: CellConfig, sim_cfg: SimConfig | None = None, *,
                      on_point: Callable[[ProbedPoint], None] | None = None, timeout_s: float = 120.0) -> AlignResult:
    """Probe and align on the CNC of `cell` from a worker thread, on an event loop of its own (the
    routine's fitting, ICP, must not hold up the controller's loop): the touches planned on the
    workpiece of `sim_cfg` (default config/sim.yaml); a CellError when it takes over `timeout_s`
    (the TUI's Align screen on a robot cell, whose state machine has no probing state)."""
    plan = workpiece_probe_plan(sim_cfg or load_sim())   # the routine loads here (ICP, trimesh)

    async def run() -> AlignResult:
        return await asyncio.wait_for(align_at(cell.devices.cnc.url, cell, plan, on_point=on_point), timeout_s)
    try:
        return asyncio.run(run())
    except asyncio.TimeoutError:
        raise CellError(f"alignment: the probe cycle did not finish within {timeout_s:g} s; check the CNC link") from None


def workpiece_probe_plan(sim_cfg: SimConfig) -> ProbePlan:
    """The alignment routine's touches on the nominal part of a sim config's workpiece."""
    # lazy: the alignment routine (ICP, trimesh) loads only when a cell is aligned
    from controller.align.routine import cad_mesh, plan_for_mesh

    return plan_for_mesh(cad_mesh(sim_cfg.cnc.workpiece))


def aligned_job(job: CellJob, transform: ArrayLike, record: Mapping[str, object], *, name: str | None = None) -> CellJob:
    """`job` moved by an alignment's transform (the CAD model moves, not the part), the alignment
    recorded in it (renamed `name`, when given); a job that already carries one is refused (one
    alignment per job)."""
    # lazy: the kinematics load only when a job is aligned
    from controller.motion.kinematics import apply_to_job

    return apply_to_job(job, transform, record, name=name)


def state_machine_doc() -> str:
    """docs/state-machine.md, generated from the controller's state machine (`cell docs`)."""
    # lazy: the state machine loads only when the page is written
    from controller.runtime.machine import state_machine_doc as doc

    return doc()


def feedable_time_scale(cfg: CellConfig, job: CellJob, max_step_mm: float = 2.0) -> tuple[CellConfig, str | None]:
    """`cfg` with cell.time_scale lowered to what the CNC link can feed for `job` (simulated time
    only, CNC cells: controller/motion/cnc5.py) and the message saying so; (cfg, None) when not lowered."""
    # lazy: the 5-axis post loads only for a simulated build
    from controller.motion.cnc5 import limit_time_scale

    return limit_time_scale(cfg, job, max_step_mm)
