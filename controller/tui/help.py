"""Help screen (`?`): every key, and which commands the cell's state allows now."""
from __future__ import annotations

from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import VerticalScroll
from textual.screen import ModalScreen
from textual.widgets import Static

FIXED_KEYS = (
    ("F1..F5", "Job, Align, Build, Log, Devices screens"),
    ("Ctrl+E", "software E-STOP, from any field or dialog"),
    ("[ / ]", "previous / next layer in the preview"),
    ("q, Ctrl+C", "quit (asks first during a build; the default is to stay)"),
    ("?", "this help; Esc closes it"),
)


def help_text(command_keys: dict[str, tuple[str, str]], state: str, allowed: tuple[str, ...]) -> str:
    """The key table, with each command marked allowed or not in `state`."""
    lines = [f"[b]Keys[/b]   state now: [b]{state}[/b]", ""]
    for key, (cmd, label) in command_keys.items():
        mark = "[green]allowed now[/]" if cmd in allowed else "[dim]not in this state[/]"
        lines.append(f"  [b]{key:<10}[/b] {label:<14} {mark}")
    lines.append("")
    for key, what in FIXED_KEYS:
        lines.append(f"  [b]{key:<10}[/b] {what}")
    return "\n".join(lines)


class HelpScreen(ModalScreen[None]):
    """Keys and what the state allows."""

    DEFAULT_CSS = """
    HelpScreen { align: center middle; }
    HelpScreen > VerticalScroll { width: 72; max-height: 90%; height: auto; border: thick $accent;
                                  padding: 1 2; background: $surface; }
    """
    BINDINGS = [Binding("escape", "close", "Close"), Binding("question_mark", "close", "Close")]

    def __init__(self, text: str) -> None:
        super().__init__()
        self._text = text

    def compose(self) -> ComposeResult:
        with VerticalScroll():
            yield Static(self._text, id="help-text")

    def action_close(self) -> None:
        self.dismiss(None)
