"""`cell records query`: what a quality engineer asks of the store (docs/records.md).

Builds (default) or, with `defects`, the beads with a defect, filtered by material, wire lot, cell
and start date; each row with its cell, job, material, wire lot, and for builds the arc time and
heat input of the part. The filters are on `builds` (indexed by lot, material, cell and start);
the defective beads are found through a partial index on `beads`, so the answer never scans the
bead table (bench/records_query.py: 10^6 bead rows).
"""
from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any

from controller.records.db import Store
from core.errors import InputError

BUILD_OUT = ("build_id", "cell", "job_name", "job_hash", "material", "wire_lot", "gas", "operator", "started",
             "ended", "state", "layers_done", "passes_done", "arc_time_s", "heat_input_kj", "heat_input_j_mm",
             "deposit_length_mm", "bead_defects", "alarms")
BEAD_OUT = ("layer", "pass", "role", "status", "defects_count", "defect_reasons", "arc_time_s", "current_mean_a",
            "voltage_mean_v", "wfs_mean_m_min", "speed_measured_mm_min", "heat_input_j_mm")
BEAD_BUILD = ("build_id", "cell", "job_name", "material", "wire_lot", "operator", "started")


@dataclass(frozen=True)
class Filters:
    material: str | None = None
    wire_lot: str | None = None
    cell: str | None = None
    since: str | None = None     # ISO 8601 (UTC when no offset is given)
    limit: int = 10000


def since_arg(text: str) -> str:
    """--since DATE: an ISO date or date-time, as the ISO text the store's `started` is compared with."""
    try:
        t = dt.datetime.fromisoformat(text.strip())
    except ValueError:
        raise InputError(f"--since {text!r}: not a date; give YYYY-MM-DD or YYYY-MM-DDTHH:MM[:SS][+HH:MM]") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.timezone.utc)
    return t.astimezone(dt.timezone.utc).isoformat()


def _where(f: Filters) -> tuple[str, list[Any]]:
    conds, params = [], []
    for col, v in (("b.material", f.material), ("b.wire_lot", f.wire_lot), ("b.cell", f.cell)):
        if v is not None:
            conds.append(f"{col} = ?")
            params.append(v)
    if f.since is not None:
        conds.append("b.started >= ?")
        params.append(f.since)
    return (" WHERE " + " AND ".join(conds)) if conds else "", params


def builds(store: Store, f: Filters) -> list[dict[str, Any]]:
    """One row per build (newest first) with its arc time and heat input."""
    where, params = _where(f)
    cols = ", ".join(f"b.{c}" for c in BUILD_OUT)
    rows = store.rows(f"SELECT {cols} FROM builds b{where} ORDER BY b.started DESC, b.build_id LIMIT ?",
                      (*params, f.limit))
    return [dict(zip(BUILD_OUT, r)) for r in rows]


def defective_beads(store: Store, f: Filters) -> list[dict[str, Any]]:
    """One row per bead with a defect, with its build's cell, job, material, lot and operator."""
    where, params = _where(f)
    where = (where + " AND" if where else " WHERE") + " d.defects_count > 0"
    cols = ", ".join([f"b.{c}" for c in BEAD_BUILD] + [f"d.{c}" for c in BEAD_OUT])
    rows = store.rows(f"SELECT {cols} FROM builds b JOIN beads d ON d.build_id = b.build_id{where} "
                      "ORDER BY b.started DESC, b.build_id, d.seq LIMIT ?", (*params, f.limit))
    return [dict(zip(BEAD_BUILD + BEAD_OUT, r)) for r in rows]
