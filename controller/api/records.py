"""The shop's record store (docs/records.md) without a cell session: the records a runs
directory still has queued sent, one run's record sent again, builds and defective beads
queried (`cell records sync/query`, the demo)."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from controller.records.db import redact
from controller.records.query import Filters, since_arg

if TYPE_CHECKING:
    from controller.records.queue import SyncResult

__all__ = ["Filters", "query_records", "redact", "resend_record", "since_arg", "sync_records"]


def sync_records(runs_dir: Path, url: str, *, cell: str, timeout_s: float) -> SyncResult:
    """Every record queued under `runs_dir` sent to the store at `url` (idempotent); a run whose
    build ended without its record gets it from its journal first."""
    # lazy: the queue and the report load only when records are sent
    from controller.api.offline import write_run_report
    from controller.records.queue import pending_dirs, sync

    dirs = pending_dirs([runs_dir])
    for d in dirs:   # a record the build's end could not write: from the journal now
        if not (d / "report.json").is_file() and (d / "journal.sqlite").is_file():
            write_run_report(d, plots=False)
    return sync(dirs, url, cell=cell, timeout_s=timeout_s)


def resend_record(run_dir: Path, url: str, *, cell: str, timeout_s: float) -> SyncResult:
    """The record of `run_dir` sent again (its report.json changed after the build's end)."""
    # lazy: the queue loads only when records are sent
    from controller.records.queue import resend

    return resend(run_dir, url, cell=cell, timeout_s=timeout_s)


def query_records(url: str, filters: Filters, *, defects: bool = False, timeout_s: float = 5.0) -> list[dict[str, Any]]:
    """Builds (or, with `defects`, the beads with a defect) of the store at `url` that match `filters`."""
    # lazy: the store's drivers (psycopg, sqlite3) load only when the store is queried
    from controller.records.db import connect
    from controller.records.query import builds, defective_beads

    store = connect(url, timeout_s)
    try:
        return defective_beads(store, filters) if defects else builds(store, filters)
    finally:
        store.close()
