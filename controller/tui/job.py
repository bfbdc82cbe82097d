"""Job screen: the open part or job, planning progress, summary, per-role parameters, layer preview."""
from __future__ import annotations

from textual.app import ComposeResult
from textual.containers import Horizontal, Vertical
from textual.widgets import DataTable, ProgressBar, Static

from controller.tui.widgets import LayerPreview, fmt, put
from controller.tui.session import View
from controller.tui.view import JobInfo

SUMMARY_KEYS = (("layers", "layers", ""), ("passes", "passes", ""), ("arc_starts", "arc starts", ""),
                ("deposit_length_mm", "deposit length", " mm"), ("volume_mm3", "volume", " mm³"),
                ("coverage", "coverage", ""), ("est_time_s", "estimated time", " s"))


class JobPane(Vertical):
    """What will be built: press o to open, g to plan."""

    DEFAULT_CSS = """
    JobPane #job-file { height: auto; }
    JobPane #plan-progress { height: 1; margin: 0 0 1 0; }
    JobPane #job-left { width: 66; height: 1fr; overflow-y: auto; }
    JobPane #job-preview { width: 1fr; height: 1fr; }
    JobPane #job-summary { height: auto; margin-bottom: 1; }
    JobPane #job-roles { height: auto; max-height: 6; }
    """

    def __init__(self) -> None:
        super().__init__(id="job-pane")
        self.preview_layer: int = 0
        self._roles_key: object = None

    def compose(self) -> ComposeResult:
        yield Static("", id="job-file")
        yield ProgressBar(total=1, show_eta=False, id="plan-progress")
        with Horizontal():
            with Vertical(id="job-left"):
                yield Static("", id="job-summary")
                yield DataTable(id="job-roles", cursor_type="none", zebra_stripes=False)
            yield LayerPreview(id="job-preview")

    def on_mount(self) -> None:
        t = self.query_one("#job-roles", DataTable)
        t.add_columns("role", "passes", "width mm", "current A", "speed mm/min", "WFS m/min")

    def step_layer(self, delta: int, view: View) -> None:
        if view.job is not None:
            self.preview_layer = max(0, min(view.job.layers - 1, self.preview_layer + delta))

    def refresh_view(self, v: View) -> None:
        put(self.query_one("#job-file", Static), _headline(v))
        _show_progress(self.query_one("#plan-progress", ProgressBar), v)
        j = v.job
        if j is None:
            put(self.query_one("#job-summary", Static), "")
            self.query_one(LayerPreview).show((), None)
            return
        put(self.query_one("#job-summary", Static), "\n".join(_summary_lines(j)))
        if self._roles_key is not j.roles:
            self._roles_key = j.roles
            self._show_roles(j)
        self.preview_layer = min(self.preview_layer, j.layers - 1)
        self.query_one(LayerPreview).show(j.layer_paths, self.preview_layer, 0,
                                          f"layer {self.preview_layer + 1}/{j.layers}  ([ ] to step)")

    def _show_roles(self, j: JobInfo) -> None:
        t = self.query_one("#job-roles", DataTable)
        t.clear()
        for r in j.roles:
            t.add_row(r.role, str(r.passes), fmt(r.width_mm, 2), _rng(r.current_a, 0), _rng(r.speed_mm_min, 0),
                      _rng(r.wfs_m_min, 2))


def _headline(v: View) -> str:
    """The line above the progress bar: what is open and what to press next."""
    p = v.plan
    if p.state == "none" and v.job is None:
        return "No part or job open. Press [b]o[/b] to open an STL part (the demo part is offered) or a job file."
    if p.state == "loaded":
        return f"Part [b]{p.file}[/b] loaded, bead width {fmt(p.width_mm, 1)} mm. Press [b]g[/b] to plan it."
    if p.state == "planning":
        return f"Planning [b]{p.file}[/b]: layer {p.done} of {p.total or '?'}…"
    if p.state == "error":
        return f"[red]Planning failed:[/red] {p.error}"
    return f"Job [b]{v.job.name if v.job else '?'}[/b] open" + (f" (from {p.file})" if p.file else "") \
        + ". Press [b]s[/b] to start" + (" or [b]l[/b] to align first." if v.can_probe else ".")


def _show_progress(bar: ProgressBar, v: View) -> None:
    p = v.plan
    if p.state == "planning":
        bar.update(total=max(p.total, 1), progress=p.done)
    elif p.state == "done" or v.job is not None:
        bar.update(total=1, progress=1)
    else:
        bar.update(total=1, progress=0)


def _summary_lines(j: JobInfo) -> list[str]:
    """The job's name, bead and summary figures, one per line."""
    lines = [f"[b]{j.name}[/b]  source {j.source}"]
    b = j.bead
    if b:
        lines.append(f"bead {fmt(b.get('width_mm'), 2)} × {fmt(b.get('height_mm'), 2)} mm, "
                     f"step-over {fmt(b.get('step_over_mm'), 2)} mm ({b.get('model', '')})")
    for key, label, unit in SUMMARY_KEYS:
        if key in j.summary:
            val = j.summary[key]
            txt = f"{val:.3f}" if key == "coverage" else (f"{val:,.0f}" if isinstance(val, float) else str(val))
            lines.append(f"{label:<16}{txt}{unit}")
    return lines


def _rng(r: tuple[float, float], nd: int) -> str:
    lo, hi = r
    return fmt(lo, nd) if abs(hi - lo) < 10 ** -nd else f"{fmt(lo, nd)}–{fmt(hi, nd)}"
