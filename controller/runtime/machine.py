"""The cell's strict state machine (docs/contract.md §6): an explicit transition table.

An event that is not in the table for the current state is refused with `TransitionRefused`
(a CellError that names the event, the state and what is allowed), never silently ignored.
Running is split into its sub-states so the operator and the journal see exactly where a
build stands: `running_wait` (pre-layer / interpass wait), `running_travel`,
`running_arc_start`, `running_depositing`, `running_arc_end`.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from enum import Enum
from typing import Callable

from core.errors import CellError


class State(str, Enum):
    DISCONNECTED = "disconnected"
    IDLE = "idle"
    HOMING = "homing"
    PROBING = "probing"
    ALIGNED = "aligned"
    READY = "ready"
    RUNNING_WAIT = "running_wait"            # pre-layer / interpass wait
    RUNNING_TRAVEL = "running_travel"        # approach to the start of the next bead
    RUNNING_ARC_START = "running_arc_start"  # arc start handshake, motion waits at WAIT
    RUNNING_DEPOSITING = "running_depositing"
    RUNNING_ARC_END = "running_arc_end"      # crater, burn-back, post-flow
    PAUSED = "paused"
    FAULT = "fault"
    ESTOP = "estop"
    COMPLETE = "complete"
    ABORTED = "aborted"

    @property
    def running(self) -> bool:
        return self.value.startswith("running_")


S = State
RUNNING = (S.RUNNING_WAIT, S.RUNNING_TRAVEL, S.RUNNING_ARC_START, S.RUNNING_DEPOSITING, S.RUNNING_ARC_END)
# Where a fault can be latched: wherever a device is driven or watched.
_FAULTABLE = (S.IDLE, S.HOMING, S.PROBING, S.ALIGNED, S.READY, *RUNNING, S.PAUSED)


class TransitionRefused(CellError):
    """An event that is not allowed in the current state."""


@dataclass(frozen=True)
class Transition:
    event: str
    sources: tuple[State, ...]
    target: State
    doc: str = ""


# The table. Order matters only for the diagram.
TRANSITIONS: tuple[Transition, ...] = (
    Transition("connect", (S.DISCONNECTED,), S.IDLE, "all devices answer"),
    Transition("disconnect", (S.IDLE, S.ALIGNED, S.READY, S.COMPLETE, S.ABORTED, S.FAULT), S.DISCONNECTED),
    Transition("home", (S.IDLE, S.ALIGNED, S.COMPLETE, S.ABORTED), S.HOMING),
    Transition("homed", (S.HOMING,), S.IDLE),
    Transition("probe", (S.IDLE, S.ALIGNED, S.READY), S.PROBING, "run the alignment routine"),
    Transition("aligned", (S.PROBING,), S.ALIGNED, "transform found"),
    Transition("open_job", (S.IDLE, S.ALIGNED, S.READY, S.COMPLETE, S.ABORTED), S.READY, "job loaded and checked"),
    Transition("start", (S.READY,), S.RUNNING_WAIT, "start or resume a build"),
    Transition("travel", (S.RUNNING_WAIT, S.RUNNING_ARC_END), S.RUNNING_TRAVEL, "approach the next bead"),
    Transition("arc_start", (S.RUNNING_TRAVEL,), S.RUNNING_ARC_START, "weld start"),
    Transition("arc_on", (S.RUNNING_ARC_START,), S.RUNNING_DEPOSITING, "motion release, !GO"),
    Transition("arc_end", (S.RUNNING_DEPOSITING,), S.RUNNING_ARC_END, "last weld move executed"),
    Transition("next_layer", (S.RUNNING_ARC_END, S.RUNNING_TRAVEL), S.RUNNING_WAIT, "layer done: interpass rule"),
    Transition("pause", (S.RUNNING_WAIT, S.RUNNING_ARC_END), S.PAUSED, "operator pause, at the end of a bead"),
    Transition("resume", (S.PAUSED,), S.RUNNING_WAIT),
    Transition("complete", (S.RUNNING_WAIT, S.RUNNING_ARC_END), S.COMPLETE, "last bead done"),
    Transition("abort", (S.READY, S.RUNNING_WAIT, S.RUNNING_ARC_END, S.PAUSED), S.ABORTED, "at the end of a bead"),
    Transition("fault", _FAULTABLE, S.FAULT, "interlock: motion held, weld start dropped"),
    Transition("estop", tuple(s for s in State if s not in (S.ESTOP, S.DISCONNECTED)), S.ESTOP, "E-stop pressed"),
    Transition("reset", (S.FAULT,), S.IDLE, "explicit operator reset"),
    Transition("reset", (S.ESTOP,), S.IDLE, "explicit reset, E-stop released"),
)


def _table() -> dict[tuple[State, str], State]:
    table: dict[tuple[State, str], State] = {}
    for t in TRANSITIONS:
        for s in t.sources:
            assert (s, t.event) not in table, f"duplicate transition {s}/{t.event}"
            table[(s, t.event)] = t.target
    return table


TABLE = _table()
EVENTS = tuple(dict.fromkeys(t.event for t in TRANSITIONS))

Listener = Callable[[State, str, State, dict[str, object]], None]


class CellMachine:
    """The cell's state. `send(event)` moves it or raises TransitionRefused; thread-safe."""

    def __init__(self, initial: State = S.DISCONNECTED) -> None:
        self._state = State(initial)
        self._lock = threading.RLock()
        self._listeners: list[Listener] = []
        self.history: list[tuple[State, str, State]] = []

    @property
    def state(self) -> State:
        return self._state

    def can(self, event: str) -> bool:
        return (self._state, event) in TABLE

    def allowed_events(self) -> list[str]:
        return [e for e in EVENTS if (self._state, e) in TABLE]

    def send(self, event: str, **info: object) -> State:
        """Fire `event`; `info` goes to the listeners (the journal records it with the event).

        `reset` out of EStop requires `estop_released=True`: the input must be released first.
        """
        with self._lock:
            src = self._state
            if event not in EVENTS:
                raise TransitionRefused(f"unknown event '{event}'; events are: {', '.join(EVENTS)}")
            target = TABLE.get((src, event))
            if target is None:
                allowed = ", ".join(self.allowed_events()) or "none"
                raise TransitionRefused(f"'{event}' is not allowed in state {src.value} (allowed now: {allowed})")
            if src is S.ESTOP and event == "reset" and not info.get("estop_released", False):
                raise TransitionRefused("reset refused: the E-stop is still pressed; release it first")
            self._state = target
            self.history.append((src, event, target))
            listeners = list(self._listeners)
        for fn in listeners:
            fn(src, event, target, dict(info))
        return target

    def subscribe(self, fn: Listener) -> Callable[[], None]:
        """Call `fn(source, event, target, info)` after every transition; returns an unsubscribe."""
        self._listeners.append(fn)
        return lambda: self._listeners.remove(fn) if fn in self._listeners else None


def mermaid() -> str:
    """The state diagram as a Mermaid `stateDiagram-v2` block (deterministic)."""
    lines = ["stateDiagram-v2", "    [*] --> disconnected"]
    for t in TRANSITIONS:
        for s in t.sources:
            lines.append(f"    {s.value} --> {t.target.value}: {t.event}")
    lines += ["    complete --> [*]", "    aborted --> [*]"]
    return "\n".join(lines) + "\n"


def state_machine_doc() -> str:
    """The content of docs/state-machine.md, generated by `cell docs`."""
    rows = "\n".join(
        f"| `{t.event}` | {', '.join(s.value for s in t.sources)} | {t.target.value} | {t.doc} |"
        for t in TRANSITIONS
    )
    return (
        "# Controller state machine\n\n"
        "Generated by `cell docs` from `controller/runtime/machine.py`; do not edit by hand "
        "(`tests/runtime/test_machine.py` fails when this file is stale).\n\n"
        "Any event not listed for the current state is refused with an error naming the state "
        "and the events allowed there.\n\n"
        "```mermaid\n" + mermaid() + "```\n\n"
        "| event | from | to | meaning |\n|---|---|---|---|\n" + rows + "\n"
    )
