"""Is a journal file safe to open read-write? Checked read-only, before any write (issue 14).

`sqlite3.connect(path)` creates a missing file and, on a file it cannot read, leaves the caller
free to write a fresh schema over what is left: a damaged journal would be replaced by an
empty one and a resume would deposit the finished layers again. So an existing journal is first
inspected without writing (header, then `PRAGMA integrity_check` over a `mode=ro` URI), and only
a healthy one is opened read-write (`mode=rw`, never `rwc`).
"""
from __future__ import annotations

import hashlib
import json
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeAlias
from urllib.parse import quote

HEADER = b"SQLite format 3\x00"
TABLES = ("job", "moves", "progress", "passes", "beads", "events", "samples")


@dataclass(frozen=True)
class JournalHealth:
    """What a read-only look at a journal found."""

    path: Path
    exists: bool
    damage: str | None                  # None: healthy (or absent)
    wal_bytes: int = 0
    readable: dict[str, int] = field(default_factory=dict)   # table -> rows readable
    job_hash: str | None = None
    job_hash_ok: bool | None = None     # the stored job JSON still hashes to the stored hash
    passes_done: int | None = None
    last_done: tuple[int, int] | None = None   # (layer, pass) of the latest pass journaled done


def uri(path: Path, mode: str) -> str:
    """A `file:` URI of the path with `mode` (ro, rw, rwc)."""
    return f"file:{quote(str(path.resolve()))}?mode={mode}"


def _side(path: Path, suffix: str) -> Path:
    return path.with_name(path.name + suffix)


Row: TypeAlias = tuple[Any, ...]
"""One row as sqlite3 returns it."""

_Facts: TypeAlias = tuple[dict[str, int], str | None, bool | None, int | None, tuple[int, int] | None]
"""(rows per readable table, job hash, ok, passes done, last (layer, pass)) of a journal."""


def _ro_facts(path: Path) -> _Facts:
    readable: dict[str, int] = {}
    jh = ok = done = last = None
    db = sqlite3.connect(uri(path, "ro"), uri=True)
    try:
        for t in TABLES:
            try:
                readable[t] = int(db.execute(f"SELECT count(*) FROM {t}").fetchone()[0])
            except sqlite3.Error:
                pass
        try:
            row = db.execute("SELECT hash, job_json FROM job ORDER BY id LIMIT 1").fetchone()
            if row is not None:
                jh = str(row[0])
                canon = json.dumps(json.loads(row[1]), sort_keys=True, separators=(",", ":"))
                ok = hashlib.sha256(canon.encode("utf-8")).hexdigest() == jh
        except (sqlite3.Error, ValueError, TypeError):
            ok = False if jh is not None else None
        try:
            rows = db.execute("SELECT layer, pass FROM passes WHERE state='done' AND id IN "
                              "(SELECT max(id) FROM passes GROUP BY layer, pass) ORDER BY id").fetchall()
            done = len(rows)
            last = (int(rows[-1][0]), int(rows[-1][1])) if rows else None
        except sqlite3.Error:
            pass
    finally:
        db.close()
    return readable, jh, ok, done, last


COLUMNS = {
    "job": "hash, name, platform, created, job_json",
    "moves": "ticket, layer, pass, idx, kind, run, t",
    "progress": "id, ticket, layer, pass, idx, run, t",
    "passes": "id, layer, pass, state, run, t, info",
    "beads": "id, layer, pass, run, arc_on, arc_off, length_mm, speed_mm_min",
    "events": "id, t, kind, state, message, layer, pass, x, y, z, run",
    "samples": "t, current_a, voltage_v, wfs_m_min, temperature_c, layer, pass",
}


def _schema_damage(path: Path) -> str | None:
    """A table missing or lacking a column the controller reads: the journal's schema is damaged."""
    db = sqlite3.connect(uri(path, "ro"), uri=True)
    try:
        for t, cols in COLUMNS.items():
            try:
                db.execute(f"SELECT {cols} FROM {t} LIMIT 0")
            except sqlite3.Error as exc:
                return f"table {t}: {exc}"
    finally:
        db.close()
    return None


def inspect(path: str | Path) -> JournalHealth:
    """A read-only diagnosis of the journal at `path` (nothing is written to it or its WAL)."""
    p = Path(path)
    wal = _side(p, "-wal")
    wal_bytes = wal.stat().st_size if wal.exists() else 0
    if not p.exists():
        if wal.exists():
            return JournalHealth(p, False, "the database file is missing but its WAL is there", wal_bytes)
        return JournalHealth(p, False, None)
    if not p.is_file():
        return JournalHealth(p, True, "not a regular file", wal_bytes)
    with p.open("rb") as f:
        head = f.read(100)
    if len(head) == 0:
        what = f"0 bytes, with a {wal_bytes}-byte WAL" if wal_bytes else "0 bytes"
        return JournalHealth(p, True, what, wal_bytes)
    if len(head) < 100 or not head.startswith(HEADER):
        return JournalHealth(p, True, "not an SQLite database: bad header", wal_bytes)
    damage = None
    try:
        db = sqlite3.connect(uri(p, "ro"), uri=True)
        try:
            res = [r[0] for r in db.execute("PRAGMA integrity_check(5)")]
        finally:
            db.close()
        if res != ["ok"]:
            damage = "integrity check: " + "; ".join(str(r) for r in res)[:200]
    except sqlite3.Error as exc:
        damage = str(exc)
    facts: _Facts = ({}, None, None, None, None)
    try:
        facts = _ro_facts(p)
    except sqlite3.Error as exc:
        damage = damage or str(exc)
    readable, jh, ok, done, last = facts
    if damage is None and "job" not in readable:
        damage = "no job table: not a cell journal"
    if damage is None:
        damage = _schema_damage(p)
    if damage is not None:
        damage = " ".join(damage.split())[:240]  # one line, whatever SQLite said
    return JournalHealth(p, True, damage, wal_bytes, readable, jh, ok, done, last)
