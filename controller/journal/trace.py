"""Traceability of a build: the wire lot, the shielding gas and the operator (docs/records.md).

They come from cell.yaml's `records:` section, overridden by the command (`--wire-lot`, `--gas`,
`--operator`) or the TUI's start dialog, and by `$CELL_OPERATOR` for the operator when neither
gives one. Every run of a build journals its own (an `events` row of kind `trace`, so a journal
written before it opens unchanged); the build record carries the latest run's and every run's.
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING, Any

from core.errors import InputError

if TYPE_CHECKING:  # annotations only
    from core.config import CellConfig

OPERATOR_ENV = "CELL_OPERATOR"


@dataclass(frozen=True)
class Trace:
    """What a build is traced to: the cell, the wire lot, the gas and the operator."""

    cell: str | None = None
    wire_lot: str | None = None
    gas: str | None = None
    operator: str | None = None

    @classmethod
    def from_config(cls, cfg: CellConfig) -> "Trace":
        r = cfg.records
        return cls(cell=cfg.cell.name, wire_lot=r.wire_lot, gas=r.gas,
                   operator=r.operator or _clean(os.environ.get(OPERATOR_ENV)))

    def given(self, *, wire_lot: str | None = None, gas: str | None = None, operator: str | None = None) -> "Trace":
        """This trace with what the command or the dialog gives (a blank or missing value keeps ours)."""
        return replace(self, wire_lot=_clean(wire_lot) or self.wire_lot, gas=_clean(gas) or self.gas,
                       operator=_clean(operator) or self.operator)

    def missing(self) -> list[str]:
        """The fields not given (wire lot, gas, operator): what the TUI's start dialog asks for."""
        return [k for k in ("wire_lot", "gas", "operator") if getattr(self, k) is None]

    def as_dict(self) -> dict[str, str | None]:
        return asdict(self)


def _clean(v: str | None) -> str | None:
    v = (v or "").strip()
    return v or None


def require_lot(cfg: CellConfig, trace: Trace) -> None:
    """`records: {require_lot: true}`: a build without a wire lot is refused (before any motion)."""
    if cfg.records.require_lot and trace.wire_lot is None:
        raise InputError("no wire lot for this build, and cell.yaml says records.require_lot: true; "
                         "give `--wire-lot LOT` (or records.wire_lot in cell.yaml, or the lot in the TUI's start dialog)")


def trace_message(trace: Trace, run: int) -> str:
    """The `trace` event's message: the run and its trace as JSON."""
    return json.dumps({"run": run, **trace.as_dict()}, sort_keys=True)


def parse_trace(message: str) -> dict[str, Any] | None:
    """One `trace` event's fields (None: not readable)."""
    try:
        d = json.loads(message)
    except ValueError:
        return None
    return d if isinstance(d, dict) else None
