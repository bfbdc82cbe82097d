"""How a command ended, for its exit code and its `--json` object (docs/contract.md §7; docs/controller.md
"Exit codes"): every `--json` command prints exactly one JSON object on every exit path.

The commands print their own object when they end normally (`emit_json` counts it). When one ends
on an error, a signal or a usage error without having printed one, `cell` prints
`{"state", "error", "exit_code"}` on stdout as well as the `error:` line on stderr.

Exit codes by cause (`code_for`): a fault after the cell moved (`core.errors.Fault`: a stall, a
failed probe point, a build that stopped in Fault) is 1; bad input, a device that cannot be
reached, a cell in use and a firmware lacking the job's axes are 2 (refused before any motion).
A build's own faults (a device error while it runs) latch the cell and end it with its state
(exit 1) through the command's own object.
"""
from __future__ import annotations

from core.errors import CellError, Fault

_state: dict[str, object] = {"emitted": 0, "error": None, "state": None}


def reset() -> None:
    _state.update(emitted=0, error=None, state=None)


def emitted() -> None:
    """A command printed its JSON object."""
    _state["emitted"] = int(str(_state["emitted"])) + 1


def has_emitted() -> bool:
    return int(str(_state["emitted"])) > 0


def error(line: str, state: str | None = None) -> None:
    """The `error:` line a command ended with and, for a fault, the cell's state (the JSON object
    carries them)."""
    _state["error"] = line[len("error: "):] if line.startswith("error: ") else line
    if state is not None:
        _state["state"] = state


def last_error() -> str | None:
    e = _state["error"]
    return None if e is None else str(e)


def code_for(exc: CellError) -> int:
    """1 for a fault after motion, 2 for bad input or a refusal before any motion."""
    return 1 if isinstance(exc, Fault) else 2


def fallback(code: int) -> dict[str, object]:
    """The object of a command that ended without printing its own."""
    state = {0: "complete", 1: "fault", 2: "refused", 3: "complete"}.get(code, "stopped" if code >= 128 else "fault")
    if _state["state"] is not None and code != 2:
        state = str(_state["state"])
    return {"state": state, "error": last_error(), "exit_code": code}
