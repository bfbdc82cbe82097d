"""Log screen: the journal's events (and this session's messages), filterable."""
from __future__ import annotations

import time

from textual.app import ComposeResult
from textual.containers import Vertical
from textual.widgets import DataTable, Input

from controller.tui.session import LogRow

KIND_STYLE = {"alarm": "red", "transition": "cyan", "info": "", "ui": "dim"}


def matches(row: LogRow, flt: str) -> bool:
    """`flt`: words that must all appear (case-insensitive); `kind:alarm` matches the kind only."""
    for word in flt.lower().split():
        if word.startswith("kind:"):
            if row.kind != word[5:]:
                return False
        elif word not in f"{row.kind} {row.state or ''} {row.message}".lower():
            return False
    return True


class LogPane(Vertical):
    """Events from the journal, newest at the bottom; type in the filter to narrow them."""

    DEFAULT_CSS = """
    LogPane #log-filter { margin-bottom: 0; }
    LogPane #log-table { height: 1fr; }
    """

    def __init__(self) -> None:
        super().__init__(id="log-pane")
        self.rows: list[LogRow] = []
        self._last_id = 0
        self._ui_seen = 0
        self._shown = 0   # rows of `rows` offered to the table (those that pass the filter are in it)
        self._run_dir: str | None = None

    def compose(self) -> ComposeResult:
        yield Input(placeholder="filter: words, or kind:alarm / kind:transition / kind:info", id="log-filter")
        yield DataTable(id="log-table", cursor_type="row")

    def on_mount(self) -> None:
        self.query_one("#log-table", DataTable).add_columns("time (UTC)", "kind", "state", "where", "message")

    def poll(self, session: object, run_dir: str | None, visible: bool = True) -> None:
        """Fetch new journal rows and session messages; append the ones that pass the filter.

        While the screen is not `visible` the rows are kept and not drawn: a table that grows
        redraws with the interpreter lock held (docs/tui.md); they are drawn when it shows."""
        if run_dir != self._run_dir:  # another job: another journal
            self._run_dir, self._last_id = run_dir, 0
            self.rows = [r for r in self.rows if r.kind == "ui" or r.id < 0]
            self._refill()
        new = list(session.log_rows(self._last_id))  # type: ignore[attr-defined]
        if new:
            self._last_id = new[-1].id
        ui = session.ui_log()  # type: ignore[attr-defined]
        for r in ui[self._ui_seen:]:
            new.append(LogRow(r.id, r.t, "ui" if r.kind == "info" else r.kind, r.state, r.message))
        self._ui_seen = len(ui)
        self.rows.extend(new)
        if visible:
            self._show_pending()

    def _show_pending(self) -> None:
        pending, self._shown = self.rows[self._shown:], len(self.rows)
        if not pending:
            return
        flt = self.query_one("#log-filter", Input).value
        t = self.query_one("#log-table", DataTable)
        for r in pending:
            if matches(r, flt):
                self._add(t, r)

    def _add(self, t: DataTable[str], r: LogRow) -> None:
        st = KIND_STYLE.get(r.kind, "")
        stamp = time.strftime("%H:%M:%S", time.gmtime(r.t)) + f".{int(r.t * 10) % 10}"
        where = f"L{r.layer + 1}" + (f" P{r.pass_ + 1}" if r.pass_ is not None else "") if r.layer is not None else ""
        kind = f"[{st}]{r.kind}[/]" if st else r.kind
        t.add_row(stamp, kind, r.state or "", where, r.message)

    def _refill(self) -> None:
        flt = self.query_one("#log-filter", Input).value
        t = self.query_one("#log-table", DataTable)
        t.clear()
        self._shown = len(self.rows)
        for r in self.rows:
            if matches(r, flt):
                self._add(t, r)
        if t.row_count:
            t.move_cursor(row=t.row_count - 1)

    def on_input_changed(self, event: Input.Changed) -> None:
        self._refill()
