"""A run without a cell session: its directory (the latest, the free space its journal needs),
what its journal holds (the job, how the run was started, where a resume picks up), a journal
checked or recovered read-only, and the build's trace (`cell run`, `cell resume`, `cell journal`)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from controller.job.model import CellJob
    from controller.journal.check import JournalHealth
    from controller.journal.recover import Recovered
    from controller.journal.space import JournalEstimate
    from core.config import CellConfig

__all__ = ["JournalHead", "check_free_space", "check_journal", "journal_head", "latest_run_dir", "recover_journal",
           "require_lot"]


@dataclass(frozen=True)
class JournalHead:
    """What a run's journal says of the run as a whole."""

    job: dict[str, Any] | None      # the job record (hash, name, platform, created, job_json); None: lost
    mode: dict[str, Any]            # how the latest run was started (`{"sim": true}`: on in-process simulators)
    resume_ticket: int | None       # the highest robot ticket executed with the arc stable (None: none)


def journal_head(path: Path) -> JournalHead:
    """The head of the journal at `path` (a damaged journal is refused, untouched)."""
    # lazy: the journal loads only when a run is resumed
    from controller.journal.store import Journal

    j = Journal(path)
    try:
        mode = j.latest_mode()
        return JournalHead(job=j.job(), mode=json.loads(mode) if mode else {},
                           resume_ticket=j.max_progress_ticket() or None)
    finally:
        j.close()


def latest_run_dir(runs_dir: str | Path) -> Path:
    """The run directory whose journal was written last (a bare `cell resume`)."""
    # lazy: the resume module loads only when a run is resumed
    from controller.runtime.resume import latest_run_dir as latest

    return latest(runs_dir)


def check_free_space(run_dir: Path, job: CellJob, max_step_mm: float, time_scale: float = 1.0) -> JournalEstimate:
    """An InputError (exit 2) naming the path, the need and the free space when the job's journal
    would not fit beside `run_dir`; checked before any device (docs/contract.md §6)."""
    # lazy: the journal's estimate loads only before a build
    from controller.journal.space import check_free_space as check

    return check(run_dir, job, max_step_mm, time_scale)


def check_journal(path: Path) -> JournalHealth:
    """What of the journal at `path` is readable, read-only (`cell journal check`)."""
    # lazy: the journal's checker loads only for `cell journal`
    from controller.journal.check import inspect

    return inspect(path)


def recover_journal(run_dir: Path, out_dir: Path, job: CellJob | None) -> Recovered:
    """What a damaged journal proves, copied into a new run directory to resume (`cell journal recover`)."""
    # lazy: the journal's recovery loads only for `cell journal recover`
    from controller.journal.recover import recover

    return recover(run_dir, out_dir, job)


def require_lot(cfg: CellConfig) -> None:
    """`records: {require_lot: true}` with no wire lot in cell.yaml's `records:` (or the command's
    --wire-lot): an InputError before any device (docs/records.md)."""
    # lazy: the trace loads only when a build is traced
    from controller.journal.trace import Trace, require_lot as require

    require(cfg, Trace.from_config(cfg))
