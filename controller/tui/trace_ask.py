"""The session's share of the start dialog (controller/tui/start_dialog.py): what to ask, the
prefill, and the answers handed to the controller as the next build's trace (docs/records.md)."""
from __future__ import annotations

from typing import Any

from controller.api import Trace
from core.config import CellConfig


class TraceAsk:
    """Mixed into CellSession: `cfg` is the cell's config, `ctl` the controller once connected."""

    cfg: CellConfig
    ctl: Any

    def trace_to_ask(self) -> list[str]:
        """What the start dialog asks for: the trace fields cell.yaml does not give."""
        return Trace.from_config(self.cfg).missing()

    def trace_values(self) -> dict[str, str | None]:
        """The dialog's prefill: the build's trace as it stands (cell.yaml's, then the last answers)."""
        trace = self.ctl.trace if self.ctl is not None else Trace.from_config(self.cfg)
        return dict(trace.as_dict())

    def set_trace(self, values: dict[str, str]) -> None:
        """The dialog's answers: the next build's wire lot, gas and operator (blank: cell.yaml's)."""
        if self.ctl is not None:
            self.ctl.trace = Trace.from_config(self.cfg).given(**values)
