"""Never lost, never twice: the queue of records not yet in the store (docs/records.md).

Before the build-end record is written, the controller leaves `records.pending.json` in the run
directory. The record writer sends report.json and removes the file once the store has it; when
the store cannot be reached the file stays, with the reason, and the record is sent by
`cell records sync` or after the next build of the cell (which sends every pending record of its
runs directory). Sending is idempotent (controller/records/send.py), so a record sent twice (a
crash between the commit and the removal, two syncs at once) is still stored once.
"""
from __future__ import annotations

import contextlib
import datetime as dt
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

from controller.records.db import Store, StoreUnreachable, connect
from controller.records.send import send_record
from core.errors import CellError

PENDING = "records.pending.json"
URL_ENV = "CELL_RECORDS_URL"          # the store's URL for the record writer (not on its command line)


@dataclass
class SyncResult:
    """What a delivery or a sync did: run directories sent (or already there), still queued, why."""

    sent: list[str] = field(default_factory=list)
    unchanged: list[str] = field(default_factory=list)
    queued: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {"sent": len(self.sent), "unchanged": len(self.unchanged), "queued": len(self.queued),
                "errors": self.errors[:20], "queued_dirs": self.queued}


def _now() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat()


def mark_pending(run_dir: Path, reason: str) -> None:
    """Queue the run directory's record (atomically: a crash leaves the old file or the new one)."""
    p = run_dir / PENDING
    old: dict[str, Any] = {}
    with contextlib.suppress(OSError, ValueError):
        old = json.loads(p.read_text(encoding="utf-8"))
    d = {"queued": old.get("queued") or _now(), "attempts": int(old.get("attempts") or 0), "reason": reason,
         "updated": _now()}
    run_dir.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f"{PENDING}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(d) + "\n", encoding="utf-8")
    tmp.replace(p)


def pending_dirs(runs: Iterable[Path]) -> list[Path]:
    """Run directories with a queued record: each given directory itself and its children."""
    out: set[Path] = set()
    for r in runs:
        if (r / PENDING).is_file():
            out.add(r)
        if r.is_dir():
            out.update(p.parent for p in r.glob(f"*/{PENDING}"))
    return sorted(out)


def _failed(run_dir: Path, why: str) -> None:
    p = run_dir / PENDING
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        d = {"queued": _now(), "attempts": 0}
    d.update(attempts=int(d.get("attempts") or 0) + 1, reason=why, updated=_now())
    with contextlib.suppress(OSError):
        p.write_text(json.dumps(d) + "\n", encoding="utf-8")


def deliver_one(store: Store, run_dir: Path, cell: str) -> str:
    """Send the run directory's report.json; remove its queue file once stored ("stored", "replaced",
    "unchanged"). CellError when there is no readable record (the file stays)."""
    marker = run_dir / PENDING
    seen = marker.read_text(encoding="utf-8") if marker.is_file() else None
    try:
        record = json.loads((run_dir / "report.json").read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CellError(f"{run_dir}: no report.json yet; `cell report {run_dir}` writes it from the journal") from None
    except (OSError, ValueError) as exc:
        raise CellError(f"{run_dir}/report.json: cannot read it ({exc})") from None
    outcome = send_record(store, record, cell=cell, run_dir=str(run_dir))
    # removed only if nobody queued it again meanwhile (a newer record: it is sent next time)
    with contextlib.suppress(OSError):
        if seen is not None and marker.read_text(encoding="utf-8") == seen:
            marker.unlink()
    return outcome


def sync(dirs: Iterable[Path], url: str, *, cell: str, timeout_s: float = 5.0,
         store: Store | None = None) -> SyncResult:
    """Send the queued record of each run directory in `dirs`; one connection for all of them.
    A store that cannot be reached leaves every one queued, each with the reason."""
    res = SyncResult()
    todo = list(dirs)
    if not todo:
        return res
    own = store is None
    try:
        st = store if store is not None else connect(url, timeout_s)
    except StoreUnreachable as exc:
        for d in todo:
            _failed(d, str(exc))
            res.queued.append(str(d))
        res.errors.append(str(exc))
        return res
    try:
        for d in todo:
            _deliver_into(st, d, cell, res)
    finally:
        if own:
            st.close()
    return res


def _deliver_into(st: Store, d: Path, cell: str, res: SyncResult) -> None:
    try:
        outcome = deliver_one(st, d, cell)
    except Exception as exc:   # noqa: BLE001  (a database error mid-way: this record stays queued)
        msg = " ".join(str(exc).split())[:300] or type(exc).__name__
        _failed(d, msg)
        res.queued.append(str(d))
        res.errors.append(f"{d}: {msg}")
        return
    (res.unchanged if outcome == "unchanged" else res.sent).append(str(d))


def after_build(run_dir: Path, runs_dir: Path | None, url: str, *, cell: str, timeout_s: float = 5.0) -> SyncResult:
    """At the end of a build: its record, then every record still queued in the cell's runs directory."""
    dirs = [run_dir] + [d for d in pending_dirs([runs_dir] if runs_dir is not None else []) if d != run_dir]
    if not (run_dir / PENDING).is_file():
        mark_pending(run_dir, "build ended: being sent")
    return sync(dirs, url, cell=cell, timeout_s=timeout_s)


def resend(run_dir: Path, url: str, *, cell: str, timeout_s: float = 5.0) -> SyncResult:
    """A record changed after its build's end (the demo adds the alignment): queue it and send it again."""
    mark_pending(run_dir, "record changed: being sent again")
    return sync([run_dir], url, cell=cell, timeout_s=timeout_s)
