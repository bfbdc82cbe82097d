"""Recover what a damaged journal still proves into a new run directory (issue 14).

The damaged journal is never written: its files (and WAL) are copied to a scratch directory
and read there, table by table in chunks of rows so one bad page loses only its own rows. The
readable rows go into a fresh journal in a new run directory, which `cell resume` continues
from: passes journaled done are skipped, started ones re-arc where their progress rows end.
When no pass record is readable the build's progress cannot be proven and recovery is refused
(resuming from layer 0 would deposit the finished layers again).
"""
from __future__ import annotations

import json
import shutil
import sqlite3
import tempfile
from dataclasses import dataclass
from pathlib import Path

from controller.job.identity import job_hash
from controller.job.model import CellJob
from controller.journal.check import Row
from controller.journal.store import SCHEMA
from core.errors import CellError

TABLES = ("job", "moves", "progress", "passes", "beads", "events", "samples")
CHUNK = 256


@dataclass(frozen=True)
class Recovered:
    """What went into the new journal."""

    run_dir: Path
    rows: dict[str, int]
    lost_chunks: dict[str, int]
    passes_done: int


def _rows(db: sqlite3.Connection, table: str) -> tuple[list[Row], int, bool]:
    """(rows, chunks lost, readable at all) of a table, read by rowid ranges."""
    try:
        top = db.execute(f"SELECT max(rowid) FROM {table}").fetchone()[0] or 0
    except sqlite3.Error:
        return [], 0, False
    rows: list[Row] = []
    lost = 0
    for lo in range(0, int(top) + 1, CHUNK):
        try:
            rows += db.execute(f"SELECT * FROM {table} WHERE rowid >= ? AND rowid < ? ORDER BY rowid",
                               (lo, lo + CHUNK)).fetchall()
        except sqlite3.Error:
            lost += 1
    return rows, lost, True


def _read_copy(src: Path) -> tuple[dict[str, list[Row]], dict[str, int], set[str]]:
    with tempfile.TemporaryDirectory() as d:
        copy = Path(d) / "journal.sqlite"
        for suffix in ("", "-wal"):
            f = src.with_name(src.name + suffix)
            if f.exists():
                shutil.copyfile(f, copy.with_name(copy.name + suffix))
        data: dict[str, list[Row]] = {}
        lost: dict[str, int] = {}
        readable: set[str] = set()
        try:
            db = sqlite3.connect(copy)
        except sqlite3.Error:
            return data, lost, readable
        try:
            for t in TABLES:
                data[t], lost[t], ok = _rows(db, t)
                if ok:
                    readable.add(t)
        finally:
            db.close()
    return data, lost, readable


def recover(run_dir: Path, out_dir: Path, job: CellJob | None) -> Recovered:
    """Copy what the journal of `run_dir` proves into a new journal under `out_dir`."""
    src = run_dir / "journal.sqlite"
    if out_dir.exists():
        raise CellError(f"{out_dir}: already exists; recovery writes only a new run directory")
    data, lost, readable = _read_copy(src)
    jrows = data.get("job") or []
    if job is not None:
        jh = job.hash
        if jrows and jrows[0][1] != jh:
            raise CellError(f"--job: the job hashes to {jh[:12]}, the journal records {str(jrows[0][1])[:12]}; "
                            "give the job this build was started with")
        jrows = [(1, jh, jrows[0][2] if jrows else "job", jrows[0][3] if jrows else "robot",
                  jrows[0][4] if jrows else 0.0, job.json)]
    elif not jrows:
        raise CellError(f"journal {src}: its job record is not readable; give the job file with --job JOB")
    else:
        stored = json.loads(jrows[0][5])
        if job_hash(stored) != jrows[0][1]:
            raise CellError(f"journal {src}: the job stored in it does not match its checksum (tampered)")
    if "passes" not in readable:
        raise CellError(f"journal {src}: no pass record is readable, so nothing proves where the build stopped; "
                        "recovery refused (a resume from layer 0 would deposit finished layers again)")
    out_dir.mkdir(parents=True)
    db = sqlite3.connect(out_dir / "journal.sqlite", isolation_level=None)
    try:
        db.execute("PRAGMA journal_mode=WAL")
        db.executescript(SCHEMA)
        db.execute("BEGIN")
        for t in TABLES:
            rows = jrows if t == "job" else data.get(t, [])
            if rows:
                marks = ",".join("?" * len(rows[0]))
                db.executemany(f"INSERT INTO {t} VALUES ({marks})", rows)
        db.execute("INSERT INTO events (t, kind, message) VALUES (strftime('%s','now'), 'info', ?)",
                   (f"recovered from the damaged journal {src}",))
        db.execute("COMMIT")
        done = db.execute("SELECT count(*) FROM passes WHERE state='done' AND id IN "
                          "(SELECT max(id) FROM passes GROUP BY layer, pass)").fetchone()[0]
    finally:
        db.close()
    rows_n = {t: len(jrows if t == "job" else data.get(t, [])) for t in TABLES}
    return Recovered(out_dir, rows_n, {k: v for k, v in lost.items() if v}, int(done))
