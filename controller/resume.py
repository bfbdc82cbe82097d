"""Resume: what is left of a build, from the job and the journal alone.

A pass journaled `done` is skipped. A pass that was started re-arcs at the last point its weld
moves reached with the arc stable (`progress` rows): the moves up to it are not sent again
(nothing twice), the ones after it are (nothing skipped). The re-arc overlap is bounded by the
distance the torch travelled with the arc on after that point: at most one weld move
(`max_step_mm`) plus the arc's burn-back / watchdog time at the travel speed.
"""
from __future__ import annotations

from pathlib import Path

from controller.build import WorkItem
from controller.journal import Journal
from planner.errors import CellError


def remaining_work(job: dict, journal: Journal) -> list[WorkItem]:
    """Every pass not yet done, in build order, each from where its bead stopped."""
    prog = journal.pass_progress()
    items: list[WorkItem] = []
    for li, layer in enumerate(job["layers"]):
        for pi, _p in enumerate(layer["passes"]):
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
