"""The record store's schema and its versioned migrations (docs/records.md).

One schema for SQLite and PostgreSQL: portable types (TEXT, INTEGER, DOUBLE PRECISION; times as
ISO 8601 UTC text, which sorts as time), the record itself kept whole as JSON text beside the
columns a query needs. `schema_migrations` holds the versions applied; `migrate` applies the
missing ones in one transaction, serialised across the cells that connect at once (an advisory
lock on PostgreSQL, BEGIN IMMEDIATE on SQLite). A migration, once released, is never edited: a
change is a new one appended to MIGRATIONS.
"""
from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from contextlib import AbstractContextManager
from typing import Any, Protocol

from core.errors import CellError


class Migrating(Protocol):
    """What a migration needs of the store (db.py: Store)."""

    def execute(self, sql: str, params: Sequence[object] = ()) -> object: ...
    def rows(self, sql: str, params: Sequence[object] = ()) -> list[tuple[Any, ...]]: ...   # row values as the driver gives them
    def transaction(self, *, lock: str | None = None) -> AbstractContextManager[None]: ...

F = "DOUBLE PRECISION"
# report.json's per-bead figures stored as columns (beads.csv's, controller/report/record.py)
BEAD_TEXT = ("role", "status", "runs", "defect_reasons")
BEAD_INT = ("still_count", "starved_count", "defects_count")
BEAD_REAL = (
    "arc_time_s", "motion_time_s", "still_time_s", "still_max_s", "length_planned_mm", "length_measured_mm",
    "current_planned_a", "current_mean_a", "current_p5_a", "current_p95_a", "current_min_a", "current_max_a",
    "voltage_window_min_v", "voltage_window_max_v", "voltage_mean_v", "voltage_p5_v", "voltage_p95_v",
    "voltage_min_v", "voltage_max_v", "wfs_planned_m_min", "wfs_mean_m_min", "wfs_p5_m_min", "wfs_p95_m_min",
    "wfs_min_m_min", "wfs_max_m_min", "speed_planned_mm_min", "speed_measured_mm_min", "heat_input_j_mm",
)
BEAD_COLUMNS = ("layer", "pass", *BEAD_TEXT, *BEAD_INT, *BEAD_REAL)

_BEADS = ", ".join([f"{c} TEXT" for c in BEAD_TEXT] + [f"{c} INTEGER" for c in BEAD_INT]
                   + [f"{c} {F}" for c in BEAD_REAL])

MIGRATIONS: tuple[tuple[int, str, tuple[str, ...]], ...] = (
    (1, "cells, builds, layers, beads, alarms, repairs", (
        "CREATE TABLE cells (name TEXT PRIMARY KEY, first_seen TEXT NOT NULL, last_seen TEXT NOT NULL)",
        "CREATE TABLE builds (build_id TEXT PRIMARY KEY, cell TEXT NOT NULL REFERENCES cells(name), "
        "job_name TEXT, job_hash TEXT NOT NULL, platform TEXT, material TEXT, wire_lot TEXT, gas TEXT, "
        "operator TEXT, started TEXT, ended TEXT, state TEXT, layers_total INTEGER, layers_done INTEGER, "
        "passes_total INTEGER, passes_done INTEGER, arc_starts INTEGER, runs INTEGER, "
        f"arc_time_s {F}, deposit_length_mm {F}, heat_input_kj {F}, heat_input_j_mm {F}, "
        "bead_defects INTEGER, alarms INTEGER, software_version TEXT, run_dir TEXT, "
        "record_sha256 TEXT NOT NULL, record TEXT NOT NULL, received TEXT NOT NULL)",
        "CREATE INDEX builds_lot ON builds (wire_lot, started)",
        "CREATE INDEX builds_material ON builds (material, started)",
        "CREATE INDEX builds_cell ON builds (cell, started)",
        "CREATE INDEX builds_started ON builds (started)",
        "CREATE TABLE layers (build_id TEXT NOT NULL REFERENCES builds(build_id) ON DELETE CASCADE, "
        f"seq INTEGER NOT NULL, layer INTEGER NOT NULL, started TEXT, interpass_temperature_c {F}, "
        f"interpass_limit_c {F}, wait_s {F}, info TEXT NOT NULL, PRIMARY KEY (build_id, seq))",
        "CREATE TABLE beads (build_id TEXT NOT NULL REFERENCES builds(build_id) ON DELETE CASCADE, "
        f"seq INTEGER NOT NULL, layer INTEGER NOT NULL, pass INTEGER NOT NULL, {_BEADS}, "
        "PRIMARY KEY (build_id, seq))",
        # `--defects` (any filter on the build): the few defective beads of the builds found, never a scan
        "CREATE INDEX beads_defective ON beads (build_id) WHERE defects_count > 0",
        "CREATE TABLE alarms (build_id TEXT NOT NULL REFERENCES builds(build_id) ON DELETE CASCADE, "
        f"seq INTEGER NOT NULL, t {F}, kind TEXT, message TEXT NOT NULL, layer INTEGER, pass INTEGER, "
        f"x {F}, y {F}, z {F}, run INTEGER, PRIMARY KEY (build_id, seq))",
        # a repair's machining and verify (docs/repair.md); the figures as columns, the whole as JSON
        "CREATE TABLE repairs (build_id TEXT PRIMARY KEY REFERENCES builds(build_id) ON DELETE CASCADE, "
        f"tool TEXT, removal_mm3 {F}, machining_time_s {F}, height_error_mean_mm {F}, height_error_max_mm {F}, "
        f"flatness_mm {F}, below_cad_max_mm {F}, verify_defects INTEGER, machining TEXT, verify TEXT)",
    )),
)
LATEST = MIGRATIONS[-1][0]


def migrate(store: Migrating) -> int:
    """Apply the migrations the store lacks (once, whoever connects first); the schema's version.
    A store newer than this controller is refused (it would write what that schema no longer means)."""
    with store.transaction(lock="cell-records-schema"):
        store.execute("CREATE TABLE IF NOT EXISTS schema_migrations (version INTEGER PRIMARY KEY, "
                      "name TEXT NOT NULL, applied TEXT NOT NULL)")
        done = {int(v) for (v,) in store.rows("SELECT version FROM schema_migrations")}
        if done and max(done) > LATEST:
            raise CellError(f"the record store's schema is version {max(done)}, newer than this controller's "
                            f"{LATEST}; update the controller")
        now = dt.datetime.now(dt.timezone.utc).isoformat()
        for version, name, statements in MIGRATIONS:
            if version in done:
                continue
            for sql in statements:
                store.execute(sql)
            store.execute("INSERT INTO schema_migrations (version, name, applied) VALUES (?, ?, ?)",
                          (version, name, now))
    return LATEST
