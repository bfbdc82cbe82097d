"""A build's record (report.json) into the store, idempotently (docs/records.md).

The build's id (report.json `build_id`: the job's hash and the moment its journal was created) is
the builds table's primary key. Sending a record the store holds already changes nothing; sending
a newer record of the same build (a resume finished it, `cell report` rewrote it) replaces the
build's rows whole, in one transaction. So a record is stored once however often it is sent, and
the store's copy is the run directory's latest.
"""
from __future__ import annotations

import datetime as dt
import hashlib
import json
from typing import Any

from controller.records.db import Store
from controller.records.schema import BEAD_COLUMNS, BEAD_TEXT
from core.errors import CellError

BUILD_COLUMNS = (
    "build_id", "cell", "job_name", "job_hash", "platform", "material", "wire_lot", "gas", "operator", "started",
    "ended", "state", "layers_total", "layers_done", "passes_total", "passes_done", "arc_starts", "runs",
    "arc_time_s", "deposit_length_mm", "heat_input_kj", "heat_input_j_mm", "bead_defects", "alarms",
    "software_version", "run_dir", "record_sha256", "record", "received",
)
REPAIR_COLUMNS = ("tool", "removal_mm3", "machining_time_s", "height_error_mean_mm", "height_error_max_mm",
                  "flatness_mm", "below_cad_max_mm", "verify_defects", "machining", "verify")


def canonical(record: dict[str, Any]) -> str:
    """The record as stored: compact JSON with sorted keys (it reads back equal to report.json)."""
    return json.dumps(record, sort_keys=True, separators=(",", ":"))


def _heat(beads: list[dict[str, Any]]) -> tuple[float | None, float | None]:
    """The part's heat input: total (kJ) and per deposited mm (J/mm), over the beads built."""
    joules = length = 0.0
    for b in beads:
        hi, mm = b.get("heat_input_j_mm"), b.get("length_measured_mm")
        if hi is not None and mm:
            joules += float(hi) * float(mm)
            length += float(mm)
    if not length:
        return None, None
    return round(joules / 1000.0, 4), round(joules / length, 3)


def build_row(record: dict[str, Any], cell: str, run_dir: str | None) -> tuple[Any, ...]:
    """The builds row of a record (cell: the record's own, else the sender's)."""
    job = record.get("job") or {}
    text = canonical(record)
    kj, j_mm = _heat(record.get("beads") or [])
    now = dt.datetime.now(dt.timezone.utc).isoformat()
    v = {**{k: record.get(k) for k in BUILD_COLUMNS}, "cell": record.get("cell") or cell, "job_name": job.get("name"),
         "job_hash": job.get("hash"), "platform": job.get("platform"), "heat_input_kj": kj, "heat_input_j_mm": j_mm,
         "alarms": len(record.get("alarms") or []), "run_dir": run_dir,
         "record_sha256": hashlib.sha256(text.encode()).hexdigest(), "record": text, "received": now}
    return tuple(v[k] for k in BUILD_COLUMNS)


def _bead_rows(bid: str, record: dict[str, Any]) -> list[tuple[Any, ...]]:
    def value(b: dict[str, Any], c: str) -> Any:
        v = b.get(c)
        return str(v) if c in BEAD_TEXT and v is not None else v   # `runs` is 1 or "1+2"
    return [(bid, i, *(value(b, c) for c in BEAD_COLUMNS)) for i, b in enumerate(record.get("beads") or [])]


def _layer_rows(bid: str, record: dict[str, Any]) -> list[tuple[Any, ...]]:
    return [(bid, i, la.get("layer"), la.get("start"), la.get("interpass_temperature_c"), la.get("interpass_limit_c"),
             la.get("wait_s"), json.dumps(la, sort_keys=True)) for i, la in enumerate(record.get("layers") or [])]


def _alarm_rows(bid: str, record: dict[str, Any]) -> list[tuple[Any, ...]]:
    out = []
    for i, a in enumerate(record.get("alarms") or []):
        x, y, z = (list(a.get("position") or []) + [None, None, None])[:3]
        out.append((bid, i, a.get("t"), a.get("state"), a.get("message") or "", a.get("layer"), a.get("pass"),
                    x, y, z, a.get("run")))
    return out


def _repair_row(bid: str, record: dict[str, Any]) -> tuple[Any, ...] | None:
    """A repair's machining and verify (report.json `repair: {machining, verify}`), when the record has them."""
    rep = record.get("repair")
    if not isinstance(rep, dict):
        return None
    m, v = rep.get("machining") or {}, rep.get("verify") or {}
    if not m and not v:
        return None
    defects = v.get("defects")
    return (bid, m.get("tool"), m.get("removal_mm3"), m.get("time_s"), v.get("height_error_mean_mm"),
            v.get("height_error_max_mm"), v.get("flatness_mm"), v.get("below_cad_max_mm"),
            len(defects) if isinstance(defects, list) else defects,
            json.dumps(m, sort_keys=True) if m else None, json.dumps(v, sort_keys=True) if v else None)


def _insert(n: int) -> str:
    return ", ".join("?" * n)


def send_record(store: Store, record: dict[str, Any], *, cell: str = "unknown", run_dir: str | None = None) -> str:
    """Store one build's record; "stored", "replaced" (a newer record of the build) or "unchanged"."""
    bid = record.get("build_id")
    if not isinstance(bid, str) or not bid:
        raise CellError(f"record of {run_dir or 'a build'}: no build_id (written before issue 39): "
                        f"`cell report {run_dir or 'RUN_DIR'}` writes it again with one")
    row = build_row(record, cell, run_dir)
    sha = row[BUILD_COLUMNS.index("record_sha256")]
    with store.transaction(lock=f"cell-records-build:{bid}"):
        store.execute("INSERT INTO cells (name, first_seen, last_seen) VALUES (?, ?, ?) ON CONFLICT (name) "
                      "DO UPDATE SET last_seen = excluded.last_seen", (row[1], row[-1], row[-1]))
        cur = store.execute(f"INSERT INTO builds ({', '.join(BUILD_COLUMNS)}) VALUES ({_insert(len(BUILD_COLUMNS))}) "
                            "ON CONFLICT (build_id) DO NOTHING", row)
        if cur.rowcount == 1:
            outcome = "stored"
        else:
            (old,) = store.rows("SELECT record_sha256 FROM builds WHERE build_id = ?", (bid,))[0]
            if old == sha:
                return "unchanged"
            for table in ("beads", "layers", "alarms", "repairs"):
                store.execute(f"DELETE FROM {table} WHERE build_id = ?", (bid,))
            sets = ", ".join(f"{c} = ?" for c in BUILD_COLUMNS[1:])
            store.execute(f"UPDATE builds SET {sets} WHERE build_id = ?", (*row[1:], bid))
            outcome = "replaced"
        store.executemany(f"INSERT INTO beads (build_id, seq, {', '.join(BEAD_COLUMNS)}) "
                          f"VALUES ({_insert(len(BEAD_COLUMNS) + 2)})", _bead_rows(bid, record))
        store.executemany("INSERT INTO layers (build_id, seq, layer, started, interpass_temperature_c, "
                          "interpass_limit_c, wait_s, info) VALUES (?, ?, ?, ?, ?, ?, ?, ?)", _layer_rows(bid, record))
        store.executemany("INSERT INTO alarms (build_id, seq, t, kind, message, layer, pass, x, y, z, run) "
                          "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", _alarm_rows(bid, record))
        rep = _repair_row(bid, record)
        if rep is not None:
            store.execute(f"INSERT INTO repairs (build_id, {', '.join(REPAIR_COLUMNS)}) "
                          f"VALUES ({_insert(len(REPAIR_COLUMNS) + 1)})", rep)
    return outcome
