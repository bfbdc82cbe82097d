"""A run directory's build record from its journal alone: `cell report`, `cell runs` (through
controller/api/) and the record worker (controller/report/worker.py).

The job is the one the journal holds (checked against the checksum stored beside it, then read
typed like a file: controller/job/read.py); a journal without one is reported from its rows alone.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from controller.job.model import CellJob
from controller.job.read import stored_job
from controller.journal.store import Journal
from controller.report.record import iso
from controller.report.summary import summarize, write_report
from core.errors import InputError


def open_run(run_dir: Path) -> Journal:
    """The journal of a run directory; InputError when there is none."""
    path = run_dir / "journal.sqlite"
    if not path.is_file():
        raise InputError(f"{run_dir}: no journal.sqlite here; give a run directory (see `cell runs`)")
    return Journal(path)


def journal_job(journal: Journal) -> CellJob | None:
    """The job a journal holds (None: it holds none)."""
    meta = journal.job() or {}
    if not meta.get("job_json"):
        return None
    return stored_job(meta["job_json"], meta["hash"], journal.path)


def write_run_report(run_dir: str | Path, job: CellJob | None = None, *, plots: bool = True,
                     state: str | None = None, operator: str | None = None,
                     csv_path: str | Path | None = None) -> Path:
    """report.json, beads.csv (and the PNGs) of `run_dir` from its journal; the path of report.json.
    `job`: the build's job (default: the one the journal holds)."""
    run_dir = Path(run_dir)
    journal = open_run(run_dir)
    try:
        if job is None:
            job = journal_job(journal)
        return write_report(journal, run_dir, job.job if job is not None else None, plots=plots, state=state,
                            operator=operator, csv_path=csv_path)
    finally:
        journal.close()


def run_rows(runs: Path) -> list[dict[str, Any]]:
    """dir, job, state, started, layers_done, layers_total, wire_lot, operator (the latest run's) of
    every run directory with a journal."""
    out = []
    for d in sorted(p.parent for p in runs.glob("*/journal.sqlite")):
        j = open_run(d)
        try:
            meta = j.job() or {}
            job = journal_job(j)
            s = summarize(j, job.job if job is not None else None)
            started, _ = j.wall_clock_span()
            trace = (j.trace_rows() or [{}])[-1]
        finally:
            j.close()
        out.append({"dir": str(d), "job": meta.get("name"), "state": s["state"], "started": iso(started),
                    "layers_done": s["layers_done"], "layers_total": s["layers_total"],
                    "wire_lot": trace.get("wire_lot"), "operator": trace.get("operator")})
    return out
