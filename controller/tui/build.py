"""Build screen: state, progress, live process values, interpass, links and alarms."""
from __future__ import annotations

import time

from textual.app import ComposeResult
from textual.containers import Horizontal, Vertical
from textual.widgets import DataTable, Label, ProgressBar, Static

from controller.api import Snapshot
from controller.tui.widgets import LayerPreview, Redraw, Trend, put
from controller.tui.session import View

STATE_STYLE = {"running": "bold black on green", "paused": "bold black on yellow", "fault": "bold white on red",
               "estop": "bold white on red", "complete": "bold black on bright_cyan",
               "aborted": "bold black on yellow", "disconnected": "bold white on grey37"}


def state_style(state: str) -> str:
    return STATE_STYLE.get("running" if state.startswith("running_") else state, "bold black on grey70")


class BuildPane(Vertical):
    """The build as it runs."""

    DEFAULT_CSS = """
    BuildPane #build-state { height: 1; }
    BuildPane #build-record { height: 1; color: $text-muted; }
    BuildPane .bar-row { height: 1; }
    BuildPane .bar-row > Label { width: 14; }
    BuildPane .bar-row > .bar-text { width: 22; height: 1; }
    BuildPane #build-left { width: 1fr; height: 1fr; overflow-y: auto; }
    BuildPane #build-preview { width: 40%; height: 1fr; }
    BuildPane #build-interpass { height: 1; margin-top: 1; }
    BuildPane #build-links { height: auto; max-height: 6; margin-top: 1; }
    BuildPane #build-alarms { height: auto; max-height: 6; margin-top: 1; }
    """

    def __init__(self) -> None:
        super().__init__(id="build-pane")
        self._links_redraw = Redraw()

    def compose(self) -> ComposeResult:
        yield Static("", id="build-state")
        yield Static("", id="build-record")
        with Horizontal():
            with Vertical(id="build-left"):
                with Horizontal(classes="bar-row"):
                    yield Label("passes")
                    yield Label("", classes="bar-text", id="passes-text")
                    yield ProgressBar(total=1, show_eta=False, show_percentage=False, id="passes-bar")
                with Horizontal(classes="bar-row"):
                    yield Label("layers")
                    yield Label("", classes="bar-text", id="layers-text")
                    yield ProgressBar(total=1, show_eta=False, show_percentage=False, id="layers-bar")
                with Horizontal(classes="bar-row"):
                    yield Label("this layer")
                    yield Label("", classes="bar-text", id="layer-text")
                    yield ProgressBar(total=1, show_eta=False, show_percentage=False, id="layer-bar")
                yield Trend("current", "A", 1, id="trend-current")
                yield Trend("voltage", "V", 2, id="trend-voltage")
                yield Trend("wire feed", "m/min", 2, id="trend-wfs")
                yield Trend("part temp.", "°C", 0, id="trend-temp")
                yield Static("", id="build-interpass")
                yield DataTable(id="build-links", cursor_type="none")
                yield Static("", id="build-alarms")
            yield LayerPreview(id="build-preview")

    def on_mount(self) -> None:
        self.query_one("#build-links", DataTable).add_columns("link", "state", "tx", "rx", "errors", "queue")

    def refresh_view(self, v: View) -> None:
        s = v.snap
        msg = f"  {s.message}" if s.message else ""
        where = ""
        if s.layer is not None:
            where = f"  layer {s.layer + 1}/{s.layers_total}"
            if s.pass_ is not None:
                where += f", pass {s.pass_ + 1}/{s.passes_in_layer}"
        put(self.query_one("#build-state", Static),
            f"[{state_style(s.state)}] {s.state.upper().replace('_', ' ')} [/] {arc_lamp(s)}"
            f"  job {s.job_name or '—'}{trace_text(s)}  arc starts {s.arc_starts}{where}{msg}")
        put(self.query_one("#build-record", Static), record_where(s))
        self._bar("passes", s.passes_done, s.passes_total)
        self._bar("layers", s.layers_done, s.layers_total)
        in_layer = (s.pass_ or 0) if s.layer is not None else 0
        if s.state == "complete":
            in_layer = s.passes_in_layer
        self._bar("layer", in_layer, s.passes_in_layer)
        hist = v.history
        arc = arc_values(s)
        self.query_one("#trend-current", Trend).show(arc[0], [h.current_a for h in hist])
        self.query_one("#trend-voltage", Trend).show(arc[1], [h.voltage_v for h in hist])
        self.query_one("#trend-wfs", Trend).show(arc[2], [h.wfs_m_min for h in hist])
        self.query_one("#trend-temp", Trend).show(s.temperature_c, [h.temperature_c for h in hist])
        put(self.query_one("#build-interpass", Static), interpass_text(v) + process_text(s))
        self._links(v)
        put(self.query_one("#build-alarms", Static), alarms_text(v))
        self._preview(v, in_layer)

    def _links(self, v: View) -> None:
        """The link table: a link up or down at once, its counters once a second."""
        links = tuple((d.device, d.connected, d.frames_tx, d.frames_rx, d.errors, d.queue_free) for d in v.devices)
        if not self._links_redraw.due(links, tuple(x[:2] for x in links)):
            return
        t = self.query_one("#build-links", DataTable)
        t.clear()
        for dev, ok, tx, rx, err, q in links:
            t.add_row(dev, "[green]up[/]" if ok else "[red]down[/]", str(tx), str(rx),
                      f"[red]{err}[/]" if err else "0", "—" if q is None else str(q))

    def _preview(self, v: View, in_layer: int) -> None:
        """The layer being built (or the last one done) with its beads so far."""
        s = v.snap
        if v.job is None:
            self.query_one(LayerPreview).show((), None)
            return
        layer = s.layer if s.layer is not None else (min(s.layers_done, v.job.layers - 1))
        self.query_one(LayerPreview).show(v.job.layer_paths, layer, in_layer if s.layer is not None else 0,
                                          f"layer {layer + 1}/{v.job.layers}")

    def _bar(self, name: str, done: int, total: int) -> None:
        put(self.query_one(f"#{name}-text", Label), f"{done} / {total}")
        self.query_one(f"#{name}-bar", ProgressBar).update(total=max(total, 1), progress=min(done, max(total, 1)))


END_STATES = ("complete", "fault", "estop", "aborted")


def build_end_line(s: Snapshot) -> str:
    """The message line when a build ends: its end state and progress (the record follows)."""
    return (f"build {s.state.upper()}: {s.passes_done}/{s.passes_total} passes, {s.layers_done}/{s.layers_total} "
            f"layers; writing the record in {s.run_dir or 'the run directory'}…")


def record_line(s: Snapshot) -> str:
    """The record writer's own line (controller/report/worker.py), once it is written or failed."""
    m = s.message or ""
    return m if (": record in " in m or ": no record written" in m) else ""


def trace_text(s: Snapshot) -> str:
    """The running build's wire lot and operator (docs/records.md); nothing when none was given."""
    out = f"  lot {s.wire_lot}" if s.wire_lot else ""
    return out + (f"  operator {s.operator}" if s.operator else "")


def record_where(s: Snapshot) -> str:
    """Where this build's record is (or will be): the run directory, and report.json once written."""
    if s.record_path and (not s.run_dir or s.record_path.startswith(s.run_dir)):
        return f"record: {s.record_path} (beads.csv, process.png … beside it)"
    if s.run_dir:
        return f"run dir: {s.run_dir} (the record is written there when the build ends)"
    return ""


# States in which the source's last reading is not a live weld reading: the display blanks it
# rather than leave the last bead's figures on screen (they read as an arc that is still on).
NOT_SAMPLED = ("estop", "fault", "disconnected", "aborted", "complete")


def arc_lamp(s: Snapshot) -> str:
    """ARC ON lamp from the source's arc-stable bit (never from the controller's own account)."""
    if s.arc_on and s.state not in NOT_SAMPLED:
        return "[bold black on bright_green] ARC ON [/]"
    if s.arc_on is None:
        return "[dim] arc ? [/]"
    return "[dim] arc off [/]"


def arc_values(s: Snapshot) -> tuple[float | None, float | None, float | None]:
    """Current, voltage and wire feed to show: blank ('—') when the arc is off or not sampled."""
    if not s.arc_on or s.state in NOT_SAMPLED:
        return None, None, None
    return s.current_a, s.voltage_v, s.wfs_m_min


def interpass_text(v: View) -> str:
    s = v.snap
    if s.interpass_remaining_s is not None:
        return f"[yellow]interpass dwell: {s.interpass_remaining_s:.0f} s left[/] (no pyrometer reading)"
    if s.state == "running_wait" and s.temperature_c is not None and s.interpass_limit_c is not None \
            and s.temperature_c >= s.interpass_limit_c:
        return (f"[yellow]interpass wait: part {s.temperature_c:.0f} °C, "
                f"arc starts below {s.interpass_limit_c:.0f} °C[/]")
    if s.interpass_limit_c is not None:
        return f"interpass limit {s.interpass_limit_c:.0f} °C"
    return ""


def process_text(s: Snapshot) -> str:
    """The layer-height control's figures (docs/closed-loop.md), when a build gives them."""
    parts = []
    if s.stick_out_mm is not None:
        parts.append(f"stick-out {s.stick_out_mm:.2f} mm")
    if s.layer_height_error_mm is not None:
        parts.append(f"layer top {s.layer_height_error_mm:+.2f} mm vs plan")
    if s.z_correction_mm is not None:
        parts.append(f"z correction {s.z_correction_mm:+.2f} mm")
    line = ("\n" + " · ".join(parts)) if parts else ""
    path = []
    if s.path_rms_mm is not None:
        path.append(f"along the path: RMS {s.path_rms_mm:.2f} mm")
    if s.path_spread_mm is not None:
        path.append(f"spread {s.path_spread_mm:.2f} mm")
    if s.path_factor_min is not None and s.path_factor_max is not None:
        path.append(f"speed × {s.path_factor_min:.2f}–{s.path_factor_max:.2f}")
    return line + (("\n" + " · ".join(path)) if path else "")


def alarms_text(v: View, n: int = 5) -> str:
    alarms = v.snap.alarms[-n:]
    if not alarms:
        return "[dim]no alarms[/]"
    lines = [f"[b]alarms ({len(v.snap.alarms)})[/b]"]
    for a in alarms:
        where = f" (layer {a.layer + 1}, pass {a.pass_ + 1})" if a.layer is not None and a.pass_ is not None else ""
        stamp = time.strftime("%H:%M:%S", time.gmtime(a.t))
        colour = "red" if a.kind in ("fault", "estop") else "yellow"
        lines.append(f"[{colour}]{stamp} {a.kind}[/]: {a.message}{where}")
    return "\n".join(lines)
