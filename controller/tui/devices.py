"""Devices screen: each device's URL, whether its link is up, traffic, and its last error."""
from __future__ import annotations

from textual.app import ComposeResult
from textual.containers import Vertical
from textual.widgets import DataTable, Static

from controller.tui.session import View
from controller.tui.widgets import Redraw, put


class DevicesPane(Vertical):
    """The cell's devices as cell.yaml (or --sim) names them."""

    DEFAULT_CSS = """
    DevicesPane #dev-head { height: auto; margin-bottom: 1; }
    DevicesPane DataTable { height: auto; }
    """

    def __init__(self) -> None:
        super().__init__(id="devices-pane")
        self._table = Redraw()

    def compose(self) -> ComposeResult:
        yield Static("", id="dev-head")
        yield DataTable(id="dev-table", cursor_type="none")

    def on_mount(self) -> None:
        self.query_one("#dev-table", DataTable).add_columns("device", "URL", "link", "tx", "rx", "errors",
                                                            "queue free", "last error")

    def refresh_view(self, v: View) -> None:
        head = ("[b]simulated cell[/b]: the simulators run in this process on loopback ports" if v.sim
                else "devices of cell.yaml")
        if v.busy == "connecting":
            head += "\n[yellow]connecting…[/]"
        elif v.connect_error:
            head += f"\n[red]not connected:[/] {v.connect_error}\nPress [b]c[/b] to connect again."
        put(self.query_one("#dev-head", Static), head)
        # a link up or down and a new last error at once, the traffic counters once a second
        if not self._table.due(v.devices, tuple((d.device, d.url, d.connected, d.last_error) for d in v.devices)):
            return
        t = self.query_one("#dev-table", DataTable)
        t.clear()
        for d in v.devices:
            t.add_row(d.device, d.url, "[green]connected[/]" if d.connected else "[red]not connected[/]",
                      str(d.frames_tx), str(d.frames_rx), str(d.errors), "—" if d.queue_free is None else str(d.queue_free),
                      d.last_error or "")
