"""The controller's API without a cell session: the build record of a run directory, the list of
runs, and an alignment that opens and closes its own CNC link (`cell report`, `cell runs`,
`cell align run`, the demo's probe, the TUI's Align screen)."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from core.config import CellConfig, ProbeSettings

if TYPE_CHECKING:
    from controller.align.probe_cycle import ProbedPoint
    from controller.align.routine import AlignResult, ProbePlan


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
