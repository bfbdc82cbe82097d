"""The operator's terminal UI: five screens over one session, commands in the footer.

The app never reaches into the controller: it reads `View`s from its session
(controller/tui/session.py) at a fixed rate (10 Hz by default: the latest snapshot wins, so
100 Hz telemetry never queues up) and sends commands, whose refusals it shows with the
controller's own message.
"""
from __future__ import annotations

import asyncio
import concurrent.futures
from pathlib import Path
from typing import Any

from textual import on
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.css.query import NoMatches
from textual.containers import Grid, Horizontal, Vertical
from textual.events import Key
from textual.screen import ModalScreen
from textual.widgets import Button, Footer, Input, Label, Static, TabbedContent, TabPane

from controller.tui.align import AlignPane
from controller.tui.build import END_STATES, BuildPane, build_end_line, record_line, state_style
from controller.tui.devices import DevicesPane
from controller.tui.job import JobPane
from controller.tui.log import LogPane
from controller.defaults import DEMO_PART
from controller.tui.start_dialog import StartDialog
from controller.tui.session import View, freeze_heap
from controller.defaults import DEMO_WIDTH_MM
from controller.tui.help import HelpScreen, help_text
from controller.tui.widgets import put

TABS = (("job", "Job"), ("align", "Align"), ("build", "Build"), ("log", "Log"), ("devices", "Devices"))
# key -> (command, footer label). Commands of the controller and the UI's own steps.
COMMAND_KEYS = {
    "o": ("open", "Open"), "g": ("plan", "Plan"), "l": ("run_alignment", "Align"), "y": ("apply_alignment", "Apply"),
    "s": ("start", "Start"), "p": ("pause", "Pause"), "r": ("resume", "Resume"), "a": ("abort", "Abort"),
    "x": ("reset", "Reset fault"), "e": ("estop", "E-STOP"), "c": ("connect", "Connect"),
}
HIDDEN_WHEN_OFF = {"connect", "apply_alignment"}
UI_STEPS = {"open", "plan", "connect", "apply_alignment"}   # steps of the UI, not controller commands   # not dimmed but hidden when they do not apply


def _display_path(p: Path) -> str:
    try:
        return str(p.relative_to(Path.cwd()))
    except ValueError:
        return str(p)


class OpenDialog(ModalScreen[tuple[str, float] | None]):
    """Open an STL part (to plan) or a job file."""

    DEFAULT_CSS = """
    OpenDialog { align: center middle; }
    OpenDialog > Vertical { width: 72; height: auto; border: thick $accent; padding: 1 2; background: $surface; }
    OpenDialog Input { margin-bottom: 1; }
    OpenDialog Horizontal { height: auto; align-horizontal: right; }
    """
    BINDINGS = [Binding("escape", "cancel", "Cancel")]

    def __init__(self, path: str, width_mm: float) -> None:
        super().__init__()
        self._path, self._width = path, width_mm

    def compose(self) -> ComposeResult:
        with Vertical():
            yield Label("Part (STL / OBJ / 3MF) or job file (cell-job/1 JSON):")
            yield Input(self._path, id="open-path")
            yield Label("Bead width for planning (mm):")
            yield Input(f"{self._width:g}", id="open-width", type="number")
            with Horizontal():
                yield Button("Open", variant="primary", id="open-ok")
                yield Button("Cancel", id="open-cancel")

    def _result(self) -> tuple[str, float] | None:
        try:
            width = float(self.query_one("#open-width", Input).value)
        except ValueError:
            self.query_one("#open-width", Input).value = f"{self._width:g}"
            return None
        return self.query_one("#open-path", Input).value.strip(), width

    @on(Button.Pressed, "#open-ok")
    @on(Input.Submitted)
    def _ok(self) -> None:
        res = self._result()
        if res is not None:
            self.dismiss(res)

    @on(Button.Pressed, "#open-cancel")
    def action_cancel(self) -> None:
        self.dismiss(None)


class ConfirmQuit(ModalScreen[bool]):
    """Quitting during a build: the arc goes off and motion holds; the journal keeps the build."""

    DEFAULT_CSS = """
    ConfirmQuit { align: center middle; }
    ConfirmQuit > Grid { grid-size: 2; grid-gutter: 1 2; grid-rows: auto 3; width: 64; height: auto;
                         border: thick $error; padding: 1 2; background: $surface; }
    ConfirmQuit #quit-question { column-span: 2; }
    """
    BINDINGS = [Binding("escape", "stay", "Stay")]

    def compose(self) -> ComposeResult:
        with Grid():
            yield Label("A build is running. Quit now?\n\nThe weld start is dropped and motion held at once "
                        "(software E-stop). The journal keeps every bead: `cell resume` continues the build "
                        "where it stopped.", id="quit-question")
            yield Button("Stop the build and quit", variant="error", id="quit-yes")
            yield Button("Stay", variant="primary", id="quit-no")

    def on_mount(self) -> None:
        # Enter must never mean E-stop by default: the focus starts on "Stay".
        self.query_one("#quit-no", Button).focus()

    @on(Button.Pressed, "#quit-yes")
    def _yes(self) -> None:
        self.dismiss(True)

    @on(Button.Pressed, "#quit-no")
    def action_stay(self) -> None:
        self.dismiss(False)


def _demo_width_mm() -> float:
    """The demo's bead width (`cell demo`'s), offered in the open dialog."""
    return float(DEMO_WIDTH_MM)


class ConfirmAbort(ModalScreen[bool]):
    """Abort ends the build for good (a resume needs a new run): asked once, default No."""

    DEFAULT_CSS = """
    ConfirmAbort { align: center middle; }
    ConfirmAbort > Grid { grid-size: 2; grid-gutter: 1 2; grid-rows: auto 3; width: 64; height: auto;
                          border: thick $warning; padding: 1 2; background: $surface; }
    ConfirmAbort #abort-question { column-span: 2; }
    """
    BINDINGS = [Binding("escape", "keep", "Keep building")]

    def compose(self) -> ComposeResult:
        with Grid():
            yield Label("Abort the build?\n\nThe arc goes off at the end of the move and the build ends "
                        "(state aborted).", id="abort-question")
            yield Button("Abort the build", variant="warning", id="abort-yes")
            yield Button("Keep building", variant="primary", id="abort-no")

    def on_mount(self) -> None:
        self.query_one("#abort-no", Button).focus()

    @on(Button.Pressed, "#abort-yes")
    def _yes(self) -> None:
        self.dismiss(True)

    @on(Button.Pressed, "#abort-no")
    def action_keep(self) -> None:
        self.dismiss(False)


class CellApp(App[int]):
    """`cell tui`: Job, Align, Build, Log and Devices over one session."""

    TITLE = "cell"
    CSS = """
    #status { height: 1; background: $panel; }
    #message { height: 1; color: $text-muted; }
    #tabs { height: 1fr; }
    #tabs > ContentSwitcher { height: 1fr; }
    TabPane { height: 1fr; padding: 0 1; }
    """
    BINDINGS = [
        # E-STOP, Quit and Help first: a narrow footer (80 columns) cuts from the end, never these.
        Binding("e", "cmd('estop')", "E-STOP"),
        Binding("q", "quit_safe", "Quit"),
        Binding("question_mark", "help", "Help"),
        *(Binding(k, f"cmd('{c}')", label) for k, (c, label) in COMMAND_KEYS.items() if c != "estop"),
        # The software E-stop also from a text field or a dialog, where `e` is typed as a letter.
        Binding("ctrl+e", "cmd('estop')", "E-STOP", show=False, priority=True),
        Binding("ctrl+c", "quit_safe", "Quit", show=False, priority=True),
        # Screen keys work from any widget (the log filter too): priority bindings.
        *(Binding(f"f{i + 1}", f"tab('{tid}')", title, show=False, priority=True)
          for i, (tid, title) in enumerate(TABS)),
        Binding("left_square_bracket", "layer(-1)", "Prev layer", show=False),
        Binding("right_square_bracket", "layer(1)", "Next layer", show=False),
    ]

    def __init__(self, session: Any, *, refresh_hz: float = 10.0, log_hz: float = 2.0,
                 default_part: Path = DEMO_PART, default_width_mm: float | None = None) -> None:
        super().__init__()
        self.session = session
        self.refresh_hz, self.log_hz = refresh_hz, log_hz
        self.default_part = default_part
        self.default_width = default_width_mm if default_width_mm is not None else _demo_width_mm()
        self.view: View = session.view()
        self.renders = 0             # UI refreshes done (the 100 Hz test counts them)
        self.last_message = ""
        self._allowed_key: tuple[str, ...] = ()
        self._abort_confirmed = False
        self._trace_asked = False   # the start dialog was answered: the next `start` goes through
        self._quitting = False
        self.pending: set[concurrent.futures.Future[Any]] = set()
        self._prev_state: str | None = None   # to say the build's end on the message line, once
        self._record_msg = ""                 # the record line last said

    # -- layout ---------------------------------------------------------------------------------
    def compose(self) -> ComposeResult:
        yield Static("", id="status")
        with TabbedContent(initial="job", id="tabs"):
            panes = {"job": JobPane, "align": AlignPane, "build": BuildPane, "log": LogPane, "devices": DevicesPane}
            for i, (tid, title) in enumerate(TABS):
                with TabPane(f"{title} F{i + 1}", id=tid):
                    yield panes[tid]()
        yield Static("", id="message")
        yield Footer(compact=True)

    def on_mount(self) -> None:
        freeze_heap()  # the widget tree is long-lived: keep full GC passes short (see freeze_heap)
        self._watch(self.session.start(), "connect")
        self.set_interval(1.0 / self.refresh_hz, self.tick)
        self.set_interval(1.0 / self.log_hz, self.poll_log)
        self.tick()
        self.poll_log()

    # -- refresh (rate-limited: reads the latest view only) -------------------------------------
    def tick(self) -> None:
        try:
            self._tick()
        except NoMatches:  # the screen is being torn down (quitting)
            pass

    def _tick(self) -> None:
        v = self.session.view()
        self.view = v
        self.renders += 1
        s = v.snap
        self._say_build_end(s)
        sim = " [reverse] SIM [/]" if v.sim else ""
        job = f"  job {s.job_name}" if s.job_name else ""
        busy = f"  [yellow]{v.busy}…[/]" if v.busy else ""
        put(self.query_one("#status", Static),
            f"[b]cell[/b]{sim}  [{state_style(s.state)}] {s.state.upper().replace('_', ' ')} [/]{job}"
            f"  {s.passes_done}/{s.passes_total} passes{busy}")
        active = self.query_one(TabbedContent).active
        panes: dict[str, type[JobPane | AlignPane | BuildPane | DevicesPane]] = {
            "job": JobPane, "align": AlignPane, "build": BuildPane, "devices": DevicesPane}
        pane = panes.get(active)
        if pane is not None:
            self.query_one(pane).refresh_view(v)
        key = tuple(sorted(c for c, _ in COMMAND_KEYS.values() if v.allowed(c)))
        if key != self._allowed_key:
            self._allowed_key = key
            self.refresh_bindings()

    def _say_build_end(self, s: Any) -> None:
        """The message line follows the build to its end: the end state, then where the record is."""
        prev, self._prev_state = self._prev_state, s.state
        if s.state in END_STATES and prev is not None and (prev.startswith("running_") or prev == "paused"):
            self.say(build_end_line(s))
        line = record_line(s)
        if line and line != self._record_msg:
            self._record_msg = line
            self.say(line, error="no record" in line)

    def poll_log(self) -> None:
        try:
            self.query_one(LogPane).poll(self.session, self.view.snap.run_dir,
                                         visible=self.query_one(TabbedContent).active == "log")
        except NoMatches:
            pass

    def on_tabbed_content_tab_activated(self, event: TabbedContent.TabActivated) -> None:
        self.tick()
        if self.query_one(TabbedContent).active == "log":
            self.poll_log()

    def say(self, text: str, error: bool = False) -> None:
        self.last_message = text
        put(self.query_one("#message", Static), f"[red]{text}[/]" if error else text)
        if error:
            self.notify(text, severity="error", timeout=8)

    # -- commands -------------------------------------------------------------------------------
    def check_action(self, action: str, parameters: tuple[object, ...]) -> bool | None:
        if action == "cmd" and parameters:
            name = str(parameters[0])
            if self.view.allowed(name):
                return True
            if name in HIDDEN_WHEN_OFF:
                return False
            if name in ("run_alignment", "apply_alignment") and not self.view.can_probe:
                return False
            return None  # shown, dimmed
        return True

    def on_key(self, event: Key) -> None:
        # A command key whose binding is dimmed is still sent: the controller refuses it and
        # the operator reads why (its message), instead of a key that silently does nothing.
        cmd = COMMAND_KEYS.get(event.key)
        if cmd is not None and not self.view.allowed(cmd[0]) and len(self.screen_stack) == 1 \
                and not isinstance(self.focused, Input):
            event.stop()
            self.send(cmd[0])

    def action_help(self) -> None:
        s = self.view.snap
        allowed = tuple(c for c, _ in COMMAND_KEYS.values() if self.view.allowed(c))
        self.push_screen(HelpScreen(help_text(COMMAND_KEYS, s.state, allowed)))

    def action_cmd(self, name: str) -> None:
        self.send(name)

    def send(self, name: str) -> None:
        """Send a command; the controller's refusal (or the outcome) shows on the message line."""
        s = self.session
        if name in UI_STEPS and not self.view.allowed(name):
            # not a controller command: refused here, in the controller's words
            allowed = ", ".join(self.view.snap.allowed_commands) or "none"
            self.say(f"{name} refused: '{name}' is not allowed in state {self.view.snap.state} "
                     f"(allowed now: {allowed})", error=True)
            return
        try:
            if name == "abort" and self.view.allowed("abort") and not self._abort_confirmed:
                self.push_screen(ConfirmAbort(), self._abort_answer)
                return
            self._abort_confirmed = False
            if name == "open":
                self.push_screen(OpenDialog(_display_path(self.default_part), self.default_width), self._opened)
                return
            if name == "start" and self.view.allowed("start") and not self._trace_asked and s.trace_to_ask():
                # wire lot, gas, operator where cell.yaml gives none (docs/records.md)
                self.push_screen(StartDialog(s.trace_values(), s.cfg.records.require_lot), self._start_answer)
                return
            self._trace_asked = False
            if name == "plan":
                fut = s.plan()
            elif name == "connect":
                fut = s.connect()
            elif name == "apply_alignment":
                fut = s.apply_alignment()
            else:
                fut = s.command(name)
        except Exception as exc:  # a refusal before anything was sent
            self.say(f"{name}: {exc}", error=True)
            return
        self.say(f"{name}…")
        self._watch(fut, name)

    def _start_answer(self, values: dict[str, str] | None) -> None:
        if values is None:
            self.say("start: cancelled")
            return
        self.session.set_trace(values)
        self._trace_asked = True
        self.send("start")

    def _abort_answer(self, yes: bool | None) -> None:
        if yes:
            self._abort_confirmed = True
            self.send("abort")

    def _opened(self, result: tuple[str, float] | None) -> None:
        if result is None:
            return
        path, width = result
        self._watch(self.session.choose_file(path, width), "open")
        self.query_one(TabbedContent).active = "job"

    def _watch(self, fut: concurrent.futures.Future[Any], name: str) -> None:
        self.pending.add(fut)

        async def wait() -> None:
            try:
                await asyncio.wrap_future(fut)
            except Exception as exc:
                self.say(f"{name} refused: {exc}" if "not allowed" in str(exc) else f"{name}: {exc}", error=True)
            else:
                if name != "start":
                    self.say(f"{name}: done")
                elif self.view.snap.state.startswith("running_") or self.view.snap.state == "paused":
                    self.say("start: build under way")   # (a build that already ended says so itself)
            finally:
                self.pending.discard(fut)
                self.tick()
        self.run_worker(wait(), group="commands")

    def action_tab(self, tab: str) -> None:
        self.query_one(TabbedContent).active = tab

    def action_layer(self, delta: int) -> None:
        self.query_one(JobPane).step_layer(delta, self.view)
        self.tick()

    # -- quitting -------------------------------------------------------------------------------
    async def action_quit(self) -> None:
        """Textual's own quit (Ctrl+Q, the command palette) asks first too during a build."""
        self.action_quit_safe()

    def action_quit_safe(self) -> None:
        if self._quitting:
            return
        if self.session.build_active():
            self.push_screen(ConfirmQuit(), self._confirmed)
        else:
            self.run_worker(self._quit_cell(stop_build=False), group="quit")

    def _confirmed(self, yes: bool | None) -> None:
        if yes:
            self.run_worker(self._quit_cell(stop_build=True), group="quit")

    async def _quit_cell(self, stop_build: bool) -> None:
        self._quitting = True
        if stop_build:
            self.say("stopping the build: weld start dropped, motion held…")
            try:
                await asyncio.wrap_future(self.session.stop_safely())
            except Exception as exc:
                self.say(f"stop: {exc}", error=True)
        await asyncio.to_thread(self.session.close)
        self.exit(0)
