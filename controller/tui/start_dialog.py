"""The start dialog: the wire lot, gas and operator of the build, asked where cell.yaml does not
give them (docs/records.md). Prefilled with what was given last; Enter starts, Escape cancels."""
from __future__ import annotations

from textual import on
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.screen import ModalScreen
from textual.widgets import Button, Input, Label

FIELDS = (("wire_lot", "Wire lot (from the spool's label):"), ("gas", "Shielding gas (and its lot):"),
          ("operator", "Operator:"))


class StartDialog(ModalScreen[dict[str, str] | None]):
    """Ask for the build's traceability before it starts; the result is {field: value}."""

    DEFAULT_CSS = """
    StartDialog { align: center middle; }
    StartDialog > Vertical { width: 72; height: auto; border: thick $accent; padding: 1 2; background: $surface; }
    StartDialog Input { margin-bottom: 1; }
    StartDialog Horizontal { height: auto; align-horizontal: right; }
    """
    BINDINGS = [Binding("escape", "cancel", "Cancel")]

    def __init__(self, values: dict[str, str | None], require_lot: bool) -> None:
        super().__init__()
        self._values = values
        self._require_lot = require_lot

    def compose(self) -> ComposeResult:
        with Vertical():
            for name, label in FIELDS:
                need = " (required by cell.yaml)" if name == "wire_lot" and self._require_lot else ""
                yield Label(label + need)
                yield Input(self._values.get(name) or "", id=f"start-{name.replace('_', '-')}")
            with Horizontal():
                yield Button("Start", variant="primary", id="start-ok")
                yield Button("Cancel", id="start-cancel")

    @on(Button.Pressed, "#start-ok")
    @on(Input.Submitted)
    def _ok(self) -> None:
        self.dismiss({name: self.query_one(f"#start-{name.replace('_', '-')}", Input).value.strip()
                      for name, _ in FIELDS})

    @on(Button.Pressed, "#start-cancel")
    def action_cancel(self) -> None:
        self.dismiss(None)
