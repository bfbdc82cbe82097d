"""The build journal: SQLite in WAL mode with synchronous=FULL under runs/<job>/ (docs/contract.md §6).

Append-only: rows are inserted, never updated or deleted, so a `kill -9` at any moment leaves
the journal at the last committed row, and replaying the rows gives the build's state:

- `job`       the job's hash, name and canonical JSON (one row);
- `moves`     write-ahead: every weld move's ticket and the point it reaches, before it is sent;
- `progress`  a weld move executed while the arc was stable: (layer, pass, point index);
- `retractions` a device took its word back: this run's progress rows of a pass up to `upto` (a
              progress row id) beyond point `idx` no longer count (the rows themselves stay);
- `passes`    each pass's state changes (started, arc_on, done, interrupted);
- `beads`     per bead: arc-on/off times, I/U/WFS statistics, heat input (+ bead_measures, bead_extra);
- `events`    state transitions, alarms and notes, with the torch position (kind `arc`: the arc
              went unstable while depositing, which a resume must not extrapolate past);
- `samples`   I, U, WFS and part temperature, for the report's traces.

Every write is its own committed transaction; resume reads only committed rows. With
`background=True` (the controller's choice) the writes are committed in order by a writer
thread, so an fsync that takes tens of ms on a busy disk never stalls the 10 ms bus cycles;
a kill then loses at most the rows queued in the last few ms, which only makes a resumed bead
re-arc slightly earlier (never later).
"""
from __future__ import annotations

import asyncio
import json
import queue
import shutil
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

from controller.journal.check import Row, inspect, uri
from controller.journal.extra import BEAD_EXTRA
from controller.journal.queries import JournalQueries
from controller.journal.reserve import Reserve
from core.errors import CellError
from core.realtime import RT_PRIORITY, elevate

SCHEMA = """
CREATE TABLE IF NOT EXISTS job (id INTEGER PRIMARY KEY, hash TEXT NOT NULL, name TEXT NOT NULL,
    platform TEXT NOT NULL, created REAL NOT NULL, job_json TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS moves (ticket INTEGER NOT NULL, layer INTEGER NOT NULL, pass INTEGER NOT NULL,
    idx INTEGER NOT NULL, kind TEXT NOT NULL, run INTEGER NOT NULL, t REAL NOT NULL);
CREATE TABLE IF NOT EXISTS progress (id INTEGER PRIMARY KEY, ticket INTEGER NOT NULL, layer INTEGER NOT NULL,
    pass INTEGER NOT NULL, idx INTEGER NOT NULL, run INTEGER NOT NULL, t REAL NOT NULL);
CREATE TABLE IF NOT EXISTS passes (id INTEGER PRIMARY KEY, layer INTEGER NOT NULL, pass INTEGER NOT NULL,
    state TEXT NOT NULL, run INTEGER NOT NULL, t REAL NOT NULL, info TEXT NOT NULL DEFAULT '{}');
CREATE TABLE IF NOT EXISTS beads (id INTEGER PRIMARY KEY, layer INTEGER NOT NULL, pass INTEGER NOT NULL,
    run INTEGER NOT NULL, arc_on REAL NOT NULL, arc_off REAL NOT NULL, length_mm REAL NOT NULL,
    speed_mm_min REAL NOT NULL, i_mean REAL, i_min REAL, i_max REAL, u_mean REAL, u_min REAL, u_max REAL,
    wfs_mean REAL, heat_input_j_mm REAL, interrupted INTEGER NOT NULL DEFAULT 0);
CREATE TABLE IF NOT EXISTS bead_measures (id INTEGER PRIMARY KEY, layer INTEGER NOT NULL, pass INTEGER NOT NULL,
    run INTEGER NOT NULL, wfs_min REAL, wfs_max REAL, speed_mm_min REAL, motion_s REAL, moves INTEGER,
    starved INTEGER);
CREATE TABLE IF NOT EXISTS events (id INTEGER PRIMARY KEY, t REAL NOT NULL, kind TEXT NOT NULL,
    state TEXT, message TEXT NOT NULL, layer INTEGER, pass INTEGER, x REAL, y REAL, z REAL, run INTEGER);
CREATE TABLE IF NOT EXISTS samples (t REAL NOT NULL, current_a REAL, voltage_v REAL, wfs_m_min REAL,
    temperature_c REAL, layer INTEGER, pass INTEGER);
CREATE TABLE IF NOT EXISTS defects (id INTEGER PRIMARY KEY, layer INTEGER NOT NULL, pass INTEGER NOT NULL,
    run INTEGER NOT NULL, t REAL NOT NULL, reason TEXT NOT NULL, x REAL, y REAL, z REAL, measured_mm REAL);
CREATE TABLE IF NOT EXISTS bead_extra (id INTEGER PRIMARY KEY, layer INTEGER NOT NULL, pass INTEGER NOT NULL,
    run INTEGER NOT NULL, info TEXT NOT NULL DEFAULT '{}');
CREATE TABLE IF NOT EXISTS retractions (id INTEGER PRIMARY KEY, layer INTEGER NOT NULL, pass INTEGER NOT NULL,
    idx INTEGER NOT NULL, upto INTEGER NOT NULL, run INTEGER NOT NULL, t REAL NOT NULL);
CREATE INDEX IF NOT EXISTS progress_lp ON progress(layer, pass);
CREATE INDEX IF NOT EXISTS passes_lp ON passes(layer, pass);
"""


class JournalError(CellError):
    """The journal cannot be opened or does not belong to the job."""


@dataclass(frozen=True)
class PassProgress:
    """Where a pass stands according to the journal."""

    layer: int
    pass_: int
    state: str            # planned, started, arc_on, interrupted, done
    done_idx: int         # last point index reached with the arc stable (-1: none, 0: at the start)


@dataclass(frozen=True)
class PassResume:
    """What a resume needs of one pass beyond its progress rows."""

    state: str                # the latest row's state
    run: int                  # the run that wrote it
    start_mm: float | None    # where the latest run that started the pass (re-)arced, along the pass
    arc_run: int | None       # the latest run that lit the arc on the pass
    arc_unstable: bool        # that run saw the arc unstable while depositing (arc loss)
    ahead: int | None = None  # that run's robot lookahead (weld moves unexecuted; None: the window)
    stop_mm: float | None = None  # where the latest trip's deposit surely ended (`held` row), along the pass


class Journal(JournalQueries):
    """Append-only SQLite journal of one build (all runs of it: first run and every resume)."""

    def __init__(self, path: str | Path, *, background: bool = False, reserve_bytes: int = 0) -> None:
        self.path = Path(path)
        self._lock = threading.RLock()
        self._q: queue.Queue[tuple[str, Any, bool] | None] | None = None
        self._thread: threading.Thread | None = None
        self.write_errors = 0
        # a write that fails (disk full, I/O error, read-only) is a fault like a lost link
        # (docs/contract.md §6): `failed` says why (path and free space), `on_error(message)` is called
        # once, from the writer thread (the controller hands it to its loop: it trips the cell)
        self.failed: str | None = None
        self.on_error: Callable[[str], None] | None = None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # an existing journal is inspected read-only first and opened read-write only when
        # healthy: a damaged one is never overwritten, truncated or replaced (issue 14)
        health = inspect(self.path)
        if health.damage is not None:
            raise JournalError(f"journal {self.path} is damaged ({health.damage}); it was left untouched: "
                               f"`cell journal check {self.path.parent}` says what is readable")
        mode = "rw" if health.exists else "rwc"
        try:
            # autocommit mode: every execute() is its own transaction, committed at once
            self.db = sqlite3.connect(uri(self.path, mode), uri=True, isolation_level=None,
                                      check_same_thread=False)
            mode = self.db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            self.db.execute("PRAGMA synchronous=FULL")
            self.db.executescript(SCHEMA)
        except sqlite3.DatabaseError as exc:
            raise JournalError(f"journal {self.path} is damaged ({exc}); it was left untouched: "
                               f"`cell journal check {self.path.parent}` says what is readable") from None
        if str(mode).lower() != "wal":
            raise JournalError(f"{self.path}: the file system does not support SQLite WAL mode")
        self.run = self._next_run()
        # space for the rows of its own fault on a full disk (controller/journal/reserve.py)
        self._reserve = Reserve(self.path.with_name("journal.reserve"), reserve_bytes)
        try:
            self._reserve.make()
        except OSError as exc:
            self.db.close()
            raise JournalError(f"journal {self.path}: cannot hold its {reserve_bytes // 1024} kB reserve "
                               f"({exc.strerror or exc}); free space or give --runs on another disk") from None
        if background:
            self._q = queue.Queue()
            self._thread = threading.Thread(target=self._writer, name="journal", daemon=True)
            self._thread.start()

    def _writer(self) -> None:
        assert self._q is not None
        # just below the device cycles (when the cell may): a time-shared writer preempted by a
        # CPU-bound neighbour while it holds the interpreter lock would stall those cycles with it
        elevate("journal writer", RT_PRIORITY - 1)
        while True:
            item = self._q.get()
            if item is None:
                self._q.task_done()
                return
            try:
                self._do_kept(*item)
            except sqlite3.Error as exc:
                self._write_failed(exc)
            finally:
                self._q.task_done()

    def _write_failed(self, exc: BaseException) -> None:
        """A write was lost: name the path and its free space, tell `on_error` (once)."""
        self.write_errors += 1
        if self.failed is not None:
            return
        self.failed = write_failure_message(self.path, exc)
        cb = self.on_error
        if cb is not None:
            try:
                cb(self.failed)
            except Exception:
                pass

    def _do(self, sql: str, params: Any, many: bool) -> None:
        with self._lock:
            if many:
                self.db.execute("BEGIN")
                try:
                    self.db.executemany(sql, params)
                except BaseException:
                    self.db.execute("ROLLBACK")
                    raise
                self.db.execute("COMMIT")
            else:
                self.db.execute(sql, params)

    def _do_kept(self, sql: str, params: Any, many: bool) -> None:
        """`_do`; at the first write that fails, the fault is raised (`_write_failed`), the reserve
        freed and the row written again into its space (sqlite3.Error when that fails too)."""
        try:
            self._do(sql, params, many)
        except sqlite3.Error as exc:
            if not self._reserve.held:
                raise
            self._write_failed(exc)   # the fault stands, naming the free space as the write found it
            self._reserve.release()
            with self._lock:
                if self.db.in_transaction:   # a COMMIT that failed leaves its transaction open
                    self.db.execute("ROLLBACK")
            self._do(sql, params, many)

    def _write(self, sql: str, params: Any, many: bool = False) -> None:
        if self._q is not None:
            self._q.put((sql, params, many))
        else:
            try:
                self._do_kept(sql, params, many)
            except sqlite3.Error as exc:
                self._write_failed(exc)
                raise

    async def committed(self) -> None:
        """Every queued row committed (waited for off the loop); JournalError naming the path and
        its free space if a write failed: the build never ends `complete` on a partial journal."""
        await asyncio.to_thread(self.flush)
        if self.failed:
            raise JournalError(self.failed)

    def flush(self) -> None:
        """Wait until every queued write is committed (background mode)."""
        if self._q is not None:
            self._q.join()

    # -- writing -------------------------------------------------------------------------------
    def _next_run(self) -> int:
        row = self.db.execute(
            "SELECT max(r) FROM (SELECT max(run) AS r FROM passes UNION SELECT max(run) FROM moves"
            " UNION SELECT max(run) FROM events)"
        ).fetchone()
        return int(row[0] or 0) + 1

    def start_job(self, job_hash: str, name: str, platform: str, job_json: str) -> None:
        """Record the job on first use; on reuse, refuse a journal that belongs to another job."""
        self.flush()
        with self._lock:
            row = self.db.execute("SELECT hash FROM job ORDER BY id LIMIT 1").fetchone()
        if row is None:
            self._write(
                "INSERT INTO job (hash, name, platform, created, job_json) VALUES (?,?,?,?,?)",
                (job_hash, name, platform, time.time(), job_json),
            )
            self.flush()
        elif row[0] != job_hash:
            raise JournalError(
                f"{self.path} belongs to job {row[0][:8]}, not {job_hash[:8]}; use another run directory"
            )

    def job(self) -> dict[str, Any] | None:
        row = self._read1("SELECT hash, name, platform, created, job_json FROM job ORDER BY id LIMIT 1")
        if row is None:
            return None
        return {"hash": row[0], "name": row[1], "platform": row[2], "created": row[3], "job_json": row[4]}

    def moves_sent(self, rows: Iterable[tuple[int, int, int, int, str]]) -> None:
        """Write-ahead: (ticket, layer, pass, point index, kind) of moves about to be sent."""
        now = time.time()
        self._write(
            "INSERT INTO moves (ticket, layer, pass, idx, kind, run, t) VALUES (?,?,?,?,?,?,?)",
            [(tk, la, pa, ix, kind, self.run, now) for tk, la, pa, ix, kind in rows], many=True,
        )

    def progress(self, ticket: int, layer: int, pass_: int, idx: int) -> None:
        """A weld move ending at point `idx` of the pass was executed with the arc stable."""
        self._write(
            "INSERT INTO progress (ticket, layer, pass, idx, run, t) VALUES (?,?,?,?,?,?)",
            (ticket, layer, pass_, idx, self.run, time.time()),
        )

    def retract(self, layer: int, pass_: int, idx: int, why: str) -> None:
        """Withdraw this run's progress of a pass beyond point `idx`, as written so far (a device took
        its word back); appended, like every row: the writer's order makes `upto` exactly those rows."""
        self._write("INSERT INTO retractions (layer, pass, idx, upto, run, t) "
                    "SELECT ?, ?, ?, coalesce(max(id), 0), ?, ? FROM progress", (layer, pass_, idx, self.run, time.time()))
        self.event("alarm", why, layer=layer, pass_=pass_)

    def pass_state(self, layer: int, pass_: int, state: str, **info: Any) -> None:
        self._write(
            "INSERT INTO passes (layer, pass, state, run, t, info) VALUES (?,?,?,?,?,?)",
            (layer, pass_, state, self.run, time.time(), json.dumps(info, sort_keys=True)),
        )

    def bead(self, layer: int, pass_: int, *, arc_on: float, arc_off: float, length_mm: float,
             speed_mm_min: float, stats: dict[str, float | None], heat_input_j_mm: float | None,
             interrupted: bool = False) -> None:
        self._write(
            "INSERT INTO beads (layer, pass, run, arc_on, arc_off, length_mm, speed_mm_min, i_mean, i_min, i_max,"
            " u_mean, u_min, u_max, wfs_mean, heat_input_j_mm, interrupted) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
            (layer, pass_, self.run, arc_on, arc_off, length_mm, speed_mm_min,
             stats.get("i_mean"), stats.get("i_min"), stats.get("i_max"),
             stats.get("u_mean"), stats.get("u_min"), stats.get("u_max"),
             stats.get("wfs_mean"), heat_input_j_mm, int(interrupted)),
        )
        # what the beads table has no column for (added after journals were in the field: a new
        # table, so an older journal opens unchanged)
        self._write(
            "INSERT INTO bead_measures (layer, pass, run, wfs_min, wfs_max, speed_mm_min, motion_s, moves, starved)"
            " VALUES (?,?,?,?,?,?,?,?,?)",
            (layer, pass_, self.run, stats.get("wfs_min"), stats.get("wfs_max"), stats.get("speed_mm_min"),
             stats.get("motion_s"), stats.get("moves"), stats.get("starved")),
        )
        if extra := {k: stats[k] for k in BEAD_EXTRA if stats.get(k) is not None}:   # one JSON row
            self._write("INSERT INTO bead_extra (layer, pass, run, info) VALUES (?,?,?,?)",
                        (layer, pass_, self.run, json.dumps(extra)))

    def defect(self, layer: int, pass_: int, reason: str, *, pos: Sequence[float] | None = None,
               measured_mm: float | None = None) -> None:
        """A bead not deposited as planned (arc faltered, process outside tolerance): where and why."""
        x, y, z = (list(pos) + [None, None, None])[:3] if pos is not None else (None, None, None)
        self._write(
            "INSERT INTO defects (layer, pass, run, t, reason, x, y, z, measured_mm) VALUES (?,?,?,?,?,?,?,?,?)",
            (layer, pass_, self.run, time.time(), reason, x, y, z, measured_mm),
        )

    def defect_count(self) -> int:
        """Beads with a defect in this journal (every run)."""
        self.flush()
        return int(self.query("SELECT count(DISTINCT layer || '/' || pass) FROM defects")[0][0])

    def event(self, kind: str, message: str, *, state: str | None = None, layer: int | None = None,
              pass_: int | None = None, pos: Sequence[float] | None = None) -> None:
        """kind: transition, alarm, info."""
        x, y, z = (list(pos) + [None, None, None])[:3] if pos is not None else (None, None, None)
        self._write(
            "INSERT INTO events (t, kind, state, message, layer, pass, x, y, z, run) VALUES (?,?,?,?,?,?,?,?,?,?)",
            (time.time(), kind, state, message, layer, pass_, x, y, z, self.run),
        )

    def samples(self, rows: Sequence[tuple[float, float | None, float | None, float | None, float | None,
                                         int | None, int | None]]) -> None:
        """(t, current, voltage, wfs, temperature, layer, pass) rows, written in one transaction."""
        if not rows:
            return
        self._write("INSERT INTO samples VALUES (?,?,?,?,?,?,?)", list(rows), many=True)

    # -- reading -------------------------------------------------------------------------------
    def pass_progress(self) -> dict[tuple[int, int], PassProgress]:
        """The state of every pass the journal knows of (passes never started are absent)."""
        out: dict[tuple[int, int], PassProgress] = {}
        for layer, pass_, state in self.query(
            "SELECT layer, pass, state FROM passes WHERE id IN (SELECT max(id) FROM passes GROUP BY layer, pass)"
        ):
            out[(layer, pass_)] = PassProgress(layer, pass_, state, -1)
        for layer, pass_, idx in self.query(
            "SELECT layer, pass, max(idx) FROM progress p WHERE NOT EXISTS (SELECT 1 FROM retractions r WHERE "
            "r.layer = p.layer AND r.pass = p.pass AND r.run = p.run AND p.id <= r.upto AND p.idx > r.idx) "
            "GROUP BY layer, pass"
        ):
            p = out.get((layer, pass_))
            state = p.state if p else "started"
            out[(layer, pass_)] = PassProgress(layer, pass_, state, int(idx))
        return out

    def pass_resume(self, layer: int, pass_: int) -> PassResume | None:
        """The pass's latest state, its latest re-arc point and whether its last arc faltered."""
        rows = self.query("SELECT state, run, info FROM passes WHERE layer=? AND pass=? ORDER BY id", (layer, pass_))
        if not rows:
            return None
        start_mm: float | None = None
        arc_run: int | None = None
        ahead: int | None = None
        stop_mm: float | None = None
        for state, run, info in rows:
            try:
                d = json.loads(info or "{}")
            except ValueError:
                d = {}
            if state in ("started", "arc_on") and d.get("start_mm") is not None:
                start_mm = float(d["start_mm"])
            if state == "arc_on":
                arc_run = int(run)
                ahead = d.get("ahead")
            if state == "held" and d.get("stop_mm") is not None:
                stop_mm = float(d["stop_mm"])
        unstable = arc_run is not None and bool(self.query(
            "SELECT 1 FROM events WHERE kind='arc' AND layer=? AND pass=? AND run=? LIMIT 1",
            (layer, pass_, arc_run)))
        return PassResume(rows[-1][0], int(rows[-1][1]), start_mm, arc_run, unstable,
                          int(ahead) if ahead else None, stop_mm)

    def pass_tickets(self, layer: int, pass_: int, run: int) -> tuple[int, int] | None:
        """(first, last) ticket of the weld moves a run wrote ahead for a pass, None if none."""
        row = self._read1("SELECT min(ticket), max(ticket) FROM moves WHERE layer=? AND pass=? AND run=?",
                          (layer, pass_, run))
        return (int(row[0]), int(row[1])) if row and row[0] is not None else None

    def run_time_scale(self, run: int) -> float | None:
        """The time scale a run was started with (its `run` event), None if not journaled."""
        for (msg,) in self.query("SELECT message FROM events WHERE kind='run' AND run=? ORDER BY id DESC", (run,)):
            try:
                ts = json.loads(msg).get("time_scale")
            except (ValueError, AttributeError):
                continue
            if ts:
                return float(ts)
        return None

    def last_ticket(self) -> int:
        """The highest ticket ever written ahead (0 when none)."""
        row = self._read1("SELECT max(ticket) FROM moves")
        return int(row[0] or 0) if row else 0

    def move_of(self, ticket: int) -> tuple[int, int, int, str] | None:
        """(layer, pass, idx, kind) of a ticket, from the latest run that sent it."""
        row = self._read1(
            "SELECT layer, pass, idx, kind FROM moves WHERE ticket=? ORDER BY run DESC LIMIT 1", (ticket,))
        return (int(row[0]), int(row[1]), int(row[2]), str(row[3])) if row else None

    def query(self, sql: str, params: Sequence[Any] = ()) -> list[Row]:
        """Rows of a read (after every queued write is committed)."""
        self.flush()
        with self._lock:
            return list(self.db.execute(sql, params))

    def close(self) -> None:
        if self._q is not None and self._thread is not None:
            self._q.put(None)
            self._thread.join(10)
            self._q = None
        try:
            self.db.close()
        except sqlite3.Error:
            pass
        self._reserve.release()


def write_failure_message(path: Path, exc: BaseException) -> str:
    """`journal PATH: a write failed (why); N MB free on DIR`: the fault of a journal that cannot
    be written."""
    try:
        du = shutil.disk_usage(path.parent)
        free = f"{du.free / 1e6:.1f} MB free of {du.total / 1e6:.1f} MB on {path.parent}"
    except OSError as err:
        free = f"free space on {path.parent} unknown ({err.strerror or err})"
    return (f"journal {path}: a write failed ({exc}); {free}; the build was stopped "
            "(free space or fix the disk, then `cell resume`)")


def read_events_after(path: str | Path, after_id: int = 0, limit: int = 2000) -> list[Row]:
    """(id, t, kind, state, message, layer, pass) after `after_id`, on a read-only connection.

    For a reader in another thread or process (the TUI's log): WAL lets it read mid-build without
    touching the writer's connection; a journal that cannot be read yet gives no rows.
    """
    p = Path(path)
    if not p.exists():
        return []
    try:
        db = sqlite3.connect(f"file:{p}?mode=ro", uri=True, timeout=0.2)
        try:
            return db.execute("SELECT id, t, kind, state, message, layer, pass FROM events WHERE id > ? "
                              "ORDER BY id LIMIT ?", (after_id, limit)).fetchall()
        finally:
            db.close()
    except sqlite3.Error:
        return []


def count_done_readonly(path: str | Path) -> int:
    """How many passes the journal at `path` has `done`, on a read-only connection (0 if it
    cannot be read). `cell run` asks it before deciding whether a job is already complete."""
    p = Path(path)
    health = inspect(p)
    if not health.exists or health.damage is not None:
        return 0
    try:
        db = sqlite3.connect(uri(p, "ro"), uri=True)
        try:
            row = db.execute("SELECT count(*) FROM (SELECT layer, pass FROM passes WHERE id IN "
                             "(SELECT max(id) FROM passes GROUP BY layer, pass) AND state='done')").fetchone()
        finally:
            db.close()
    except sqlite3.Error:
        return 0
    return int(row[0])
