"""Resume: what is left of a build, from the job and the journal alone, and where the arc of an
interrupted bead really went out.

A pass journaled `done` is skipped. A pass that was started re-arcs where its deposit is known to
end: at least the last point its weld moves reached with the arc stable (`progress` rows) or the
point where the latest run re-arced (`start_mm` of its `started` row), whichever lies further.

When the controller died with the arc on (the pass's latest row is `arc_on`: no hold, no arc end
was journaled), the deposit went on after that point: the robot keeps executing its queue and the
power source keeps the arc until its watchdog drops the start and the burn-back ends. The build
runner re-arcs such a bead at a lower bound of where the arc went out (controller/runtime/arc_out.py),
computed once the robot has reported where it stopped.
"""
from __future__ import annotations

from pathlib import Path

from controller.runtime.work import WorkItem
from controller.job.model import CellJob
from controller.journal.store import Journal
from core.errors import CellError


def remaining_work(job: CellJob, journal: Journal) -> list[WorkItem]:
    """Every pass not yet done, in build order, each from where its bead stopped."""
    prog = journal.pass_progress()
    items: list[WorkItem] = []
    for li, layer in enumerate(job.layers):
        for pi in range(len(layer.passes)):
            p = prog.get((li, pi))
            if p is not None and p.state == "done":
                continue
            items.append(WorkItem(li, pi, max(0, p.done_idx) if p is not None else 0))
    return items


def latest_run_dir(runs_dir: str | Path) -> Path:
    """The run directory whose journal was written last (for a bare `cell resume`)."""
    cands = sorted(Path(runs_dir).glob("*/journal.sqlite"), key=lambda p: p.stat().st_mtime)
    if not cands:
        raise CellError(f"nothing to resume: no journal under {runs_dir}/ (start a build with `cell run JOB`)")
    return cands[-1].parent
