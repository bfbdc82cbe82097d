"""The controller's state machine: strict transitions, latched faults, a diagram kept in sync."""
from __future__ import annotations

from pathlib import Path

import pytest

from controller.runtime.machine import CellMachine, State, TransitionRefused, state_machine_doc

DOC = Path(__file__).resolve().parents[2] / "docs" / "state-machine.md"


def _running() -> CellMachine:
    m = CellMachine()
    for e in ("connect", "open_job", "start", "travel", "arc_start", "arc_on"):
        m.send(e)
    return m


def test_a_full_build_walks_through_every_running_substate() -> None:
    m = _running()
    assert m.state is State.RUNNING_DEPOSITING
    m.send("arc_end")
    m.send("next_layer")
    m.send("travel")
    m.send("arc_start")
    m.send("arc_on")
    m.send("arc_end")
    assert m.send("complete") is State.COMPLETE
    assert [h[2] for h in m.history][-3:] == [State.RUNNING_DEPOSITING, State.RUNNING_ARC_END, State.COMPLETE]


def test_an_event_not_allowed_is_refused_with_the_state_and_what_is_allowed() -> None:
    m = CellMachine()
    with pytest.raises(TransitionRefused, match=r"'start' is not allowed in state disconnected \(allowed now: connect"):
        m.send("start")
    assert m.state is State.DISCONNECTED
    with pytest.raises(TransitionRefused, match="unknown event"):
        m.send("fly")


def test_pause_and_abort_only_at_the_end_of_a_bead() -> None:
    m = _running()
    assert not m.can("pause") and not m.can("abort")
    with pytest.raises(TransitionRefused):
        m.send("pause")
    m.send("arc_end")
    assert m.send("pause") is State.PAUSED
    assert m.send("resume") is State.RUNNING_WAIT
    assert m.send("abort") is State.ABORTED


def test_fault_latches_until_an_explicit_reset() -> None:
    m = _running()
    m.send("fault", cause="arc loss")
    for e in ("start", "resume", "arc_on", "open_job", "fault"):
        assert not m.can(e)
    assert m.allowed_events() == ["disconnect", "estop", "reset"]
    assert m.send("reset") is State.IDLE


def test_estop_reset_needs_the_input_released() -> None:
    m = _running()
    m.send("estop")
    with pytest.raises(TransitionRefused, match="E-stop is still pressed"):
        m.send("reset", estop_released=False)
    assert m.state is State.ESTOP
    assert m.send("reset", estop_released=True) is State.IDLE


def test_listeners_see_every_transition_with_its_info() -> None:
    m = CellMachine()
    seen: list = []
    m.subscribe(lambda s, e, t, info: seen.append((s.value, e, t.value, info)))
    m.send("connect")
    m.send("fault", cause="door open")
    assert seen == [("disconnected", "connect", "idle", {}), ("idle", "fault", "fault", {"cause": "door open"})]


def test_the_diagram_in_docs_is_up_to_date() -> None:
    assert DOC.exists(), "docs/state-machine.md is missing: run `cell docs`"
    assert DOC.read_text(encoding="utf-8") == state_machine_doc(), "docs/state-machine.md is stale: run `cell docs`"
    # every state appears in the diagram
    text = DOC.read_text(encoding="utf-8")
    for s in State:
        assert f" {s.value} " in text or f" {s.value}:" in text or f"> {s.value}" in text
