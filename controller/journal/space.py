"""Free space for the journal, checked before any motion (docs/contract.md §6: the journal is part of
the safety chain; `cell run` / `cell resume` refuse, exit 2, when the runs directory cannot hold
the job's journal).

The estimate, measured on real journals (docs/controller.md, "Journal space"):
- per weld point (the job's points subdivided at --max-step): a write-ahead `moves` row and a
  `progress` row, plus the pass / bead / event rows: 103 B measured on a robot build (239 points,
  0.5 mm steps, 600 mm/min; 78-80 B/point on 2 000 and 20 000 synthetic points);
  taken as 160 B (margin 1.5);
- samples: 10 rows per wall second of arc (`sample_period_s` 0.1), about 40 B each: 600 B per s;
- the WAL: SQLite checkpoints it every 1 000 pages, so it peaks at about 4.1 MB (measured
  4 124 152 B); taken as 4.5 MB;
- the build record (report.json, CSV, four PNGs): about 0.1 MB measured; taken as 1 MB;
- the empty journal with the job stored: 48 kB plus the job's JSON;
- the reserve for the rows of the journal's own fault (controller/journal/reserve.py): 0.5 MB.
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from controller.job.model import CellJob
from controller.job.weld_path import weld_points
from controller.journal.reserve import RESERVE_BYTES
from core.errors import InputError

BYTES_PER_WELD_POINT = 160
BYTES_PER_ARC_SECOND = 600
WAL_PEAK_BYTES = 4_500_000
RECORD_BYTES = 1_000_000
BASE_BYTES = 64_000


@dataclass(frozen=True)
class JournalEstimate:
    weld_points: int
    arc_wall_s: float
    bytes: int


def journal_estimate(job: CellJob, max_step_mm: float, time_scale: float = 1.0) -> JournalEstimate:
    """Bytes the runs directory needs for this job's journal and record (see the module doc)."""
    points, arc_s = 0, 0.0
    for la in job.layers:
        for p in la.passes:
            pts = weld_points(p.points, max_step_mm)
            points += len(pts)
            arc_s += p.arc_time_s / max(time_scale, 1e-9)   # each segment at its own speed (cell-job/2)
    total = (BASE_BYTES + len(job.json) + points * BYTES_PER_WELD_POINT
             + int(arc_s * BYTES_PER_ARC_SECOND) + WAL_PEAK_BYTES + RECORD_BYTES + RESERVE_BYTES)
    return JournalEstimate(points, arc_s, total)


def check_free_space(runs_dir: Path, job: CellJob, max_step_mm: float, time_scale: float = 1.0) -> JournalEstimate:
    """Refuse (InputError, exit 2) when `runs_dir` (or its nearest existing parent) has less free
    space than the job's journal estimate; the message names the path, the need and the free."""
    est = journal_estimate(job, max_step_mm, time_scale)
    where = Path(runs_dir)
    while not where.exists() and where != where.parent:
        where = where.parent
    try:
        free = shutil.disk_usage(where).free
    except OSError as exc:
        raise InputError(f"runs directory {runs_dir}: cannot read its free space ({exc.strerror or exc})") from None
    if free < est.bytes:
        raise InputError(f"runs directory {runs_dir}: {free / 1e6:.1f} MB free on {where}, the job's journal needs "
                         f"{est.bytes / 1e6:.1f} MB ({est.weld_points} weld points, {est.arc_wall_s:.0f} s of arc, "
                         "WAL and record); free space or give --runs on another disk")
    return est
