"""The journal's read queries for the report, `cell runs`, the CLI and the TUI (the only SQL
outside the writes of controller/journal/store.py, whose `Journal` inherits them)."""
from __future__ import annotations

import json
from typing import Any, Sequence, TypeAlias

from controller.journal.check import Row
from controller.journal.extra import BEAD_EXTRA, read_extra
from controller.journal.trace import parse_trace

SampleRow: TypeAlias = tuple[float, float | None, float | None, float | None, float | None, int | None, int | None]
"""(t, current, voltage, wfs, temperature, layer, pass): one journaled process sample."""


class JournalQueries:
    """Reads over the journal's tables; `query` (committed rows only) comes from the Journal."""

    def query(self, sql: str, params: Sequence[Any] = ()) -> list[Row]:
        raise NotImplementedError   # the Journal reads after every queued write is committed

    def _read1(self, sql: str, params: Sequence[Any] = ()) -> Row | None:
        rows = self.query(sql, params)
        return rows[0] if rows else None

    def link_rows(self) -> list[dict[str, Any]]:
        """Per run, the link statistics journaled at the end of its build (late / lost / bad)."""
        out = []
        for run, msg in self.query("SELECT run, message FROM events WHERE kind='links' ORDER BY id"):
            try:
                out.append({"run": run, "links": json.loads(msg)})
            except ValueError:
                continue
        return out

    def latest_time_scale(self) -> float:
        """The time scale of the latest journaled run (1.0 when none was journaled)."""
        for (msg,) in self.query("SELECT message FROM events WHERE kind='run' ORDER BY id DESC LIMIT 1"):
            try:
                return float(json.loads(msg).get("time_scale", 1.0))
            except (ValueError, AttributeError, TypeError):
                return 1.0
        return 1.0

    def done_passes(self) -> set[tuple[int, int]]:
        """(layer, pass) of every pass whose latest state is `done`."""
        return {(la, pa) for la, pa, st in self.query(
            "SELECT layer, pass, state FROM passes WHERE id IN (SELECT max(id) FROM passes GROUP BY layer, pass)")
            if st == "done"}

    def bead_rows(self) -> list[dict[str, Any]]:
        """Every bead row as a dict (column names of the `beads` table), in the order written."""
        cols = ("layer", "pass", "run", "arc_on", "arc_off", "length_mm", "speed_mm_min", "i_mean", "i_min",
                "i_max", "u_mean", "u_min", "u_max", "wfs_mean", "heat_input_j_mm", "interrupted")
        rows = self.query(f"SELECT {', '.join(cols)} FROM beads ORDER BY id")
        out = [dict(zip(cols, r)) for r in rows]
        extra = ("wfs_min", "wfs_max", "speed_actual_mm_min", "motion_s", "moves", "starved")
        measured = {(la, pa, run): dict(zip(extra, rest)) for la, pa, run, *rest in self.query(
            "SELECT layer, pass, run, wfs_min, wfs_max, speed_mm_min, motion_s, moves, starved FROM bead_measures"
            " ORDER BY id")}
        for b in out:
            b.update(measured.get((b["layer"], b["pass"], b["run"]), dict.fromkeys(extra)))
        more = {(la, pa, run): read_extra(info) for la, pa, run, info in self.query(
            "SELECT layer, pass, run, info FROM bead_extra ORDER BY id")}
        for b in out:
            b.update({k: more.get((b["layer"], b["pass"], b["run"]), {}).get(k) for k in BEAD_EXTRA})
        return out

    def alarm_rows(self) -> list[dict[str, Any]]:
        """Alarms with their state, layer, pass, torch position and run."""
        return [
            {"t": t, "message": msg, "state": st, "layer": la, "pass": pa,
             "position": [x, y, z] if x is not None else None, "run": run}
            for t, msg, st, la, pa, x, y, z, run in self.query(
                "SELECT t, message, state, layer, pass, x, y, z, run FROM events WHERE kind='alarm' ORDER BY id")
        ]

    def last_build_state(self) -> str | None:
        """The latest journaled state other than disconnected/idle."""
        row = self._read1("SELECT state FROM events WHERE kind='transition' AND state NOT IN"
                          " ('disconnected', 'idle') ORDER BY id DESC LIMIT 1")
        return str(row[0]) if row else None

    def run_count(self) -> int:
        """How many runs (start plus resumes) wrote events."""
        row = self._read1("SELECT count(DISTINCT run) FROM events")
        return int(row[0] or 0) if row else 0

    def arc_start_count(self) -> int:
        """How many times an arc was struck on a pass."""
        row = self._read1("SELECT count(*) FROM passes WHERE state='arc_on'")
        return int(row[0] or 0) if row else 0

    def arc_on_spans(self) -> list[tuple[int, int, float, float]]:
        """(layer, pass, t arc_on, t next state) per arc strike, from the pass-state rows."""
        rows = self.query("SELECT layer, pass, state, t FROM passes ORDER BY id")
        open_: dict[tuple[int, int], float] = {}
        out: list[tuple[int, int, float, float]] = []
        for la, pa, st, t in rows:
            key = (la, pa)
            if key in open_ and st != "arc_on":
                out.append((la, pa, open_.pop(key), t))
            if st == "arc_on":
                open_[key] = t
        return out

    def sample_rows(self) -> list[SampleRow]:
        """(t, current, voltage, wfs, temperature, layer, pass) samples in time order."""
        return self.query("SELECT t, current_a, voltage_v, wfs_m_min, temperature_c, layer, pass FROM samples"
                          " ORDER BY t")

    def wall_clock_span(self) -> tuple[float | None, float | None]:
        """(first, last) wall-clock time (Unix s) of the journal's events."""
        row = self._read1("SELECT min(t), max(t) FROM events")
        return (row[0], row[1]) if row else (None, None)

    def latest_mode(self) -> str | None:
        """The message of the latest `mode` event (how the run was started), None if none."""
        row = self._read1("SELECT message FROM events WHERE kind='mode' ORDER BY id DESC LIMIT 1")
        return str(row[0]) if row else None

    def max_progress_ticket(self) -> int | None:
        """The highest ticket executed with the arc stable, None if none."""
        row = self._read1("SELECT max(ticket) FROM progress")
        return int(row[0]) if row and row[0] is not None else None

    def events_after(self, last_id: int, limit: int = 200) -> list[Row]:
        """(id, t, kind, state, message, layer, pass) of events after `last_id`."""
        return self.query("SELECT id, t, kind, state, message, layer, pass FROM events WHERE id > ? ORDER BY id"
                          " LIMIT ?", (last_id, limit))

    def trace_rows(self) -> list[dict[str, Any]]:
        """Per run, the wire lot, gas, operator and cell it was traced to (controller/journal/trace.py)."""
        out = []
        for run, t, msg in self.query("SELECT run, t, message FROM events WHERE kind='trace' ORDER BY id"):
            d = parse_trace(msg)
            if d is not None:
                out.append({"run": run, "t": t, **{k: d.get(k) for k in ("cell", "wire_lot", "gas", "operator")}})
        return out

    def defect_rows(self) -> list[dict[str, Any]]:
        """Beads the measurements say were not deposited as planned, oldest first."""
        return [{"t": t, "layer": la, "pass": pa, "reason": reason, "run": run, "measured_mm": mm,
                 "position": [x, y, z] if x is not None else None}
                for t, la, pa, reason, x, y, z, run, mm in self.query(
                    "SELECT t, layer, pass, reason, x, y, z, run, measured_mm FROM defects ORDER BY id")]
