"""Snapshot tests of the operator UI's five screens, on a recorded (fixed) view: no clock, no devices.

Regenerate after an intended change of the layout with
`.venv/bin/python -m pytest tests/tui/test_tui_snapshots.py --snapshot-update` and look at the SVGs
in tests/__snapshots__/test_tui_snapshots/ before committing them.
"""
from __future__ import annotations


import pytest

from controller.runtime.events import Alarm
from controller.tui.app import CellApp
from controller.tui.session import ReplaySession, View
from tests.tui.recorded import T0, recorded_view, recorded_log

SIZE = (120, 36)


def _app(view: View | None = None) -> CellApp:
    return CellApp(ReplaySession(view or recorded_view(), recorded_log()))


@pytest.mark.parametrize("tab", ["f1", "f2", "f3", "f4", "f5"])
def test_screen_snapshot(snap_compare, tab: str) -> None:
    """Each screen, drawn from the same recorded view, looks as it was approved."""
    assert snap_compare(_app(), press=[tab, "_"], terminal_size=SIZE)


def test_fault_state_snapshot(snap_compare) -> None:
    """A latched fault: red state banner, alarm listed, Reset fault available, Start/Pause dimmed."""
    view = recorded_view(state="fault", allowed_commands=("reset", "estop"), current_a=0.0, voltage_v=0.0,
                         alarms=(Alarm(T0 + 131.0, "fault", "door opened during the build", layer=1, pass_=2),))
    assert snap_compare(_app(view), press=["f3", "_"], terminal_size=SIZE)


@pytest.mark.parametrize("size", [(160, 48), (80, 24)])
@pytest.mark.parametrize("tab", ["f1", "f2", "f3", "f4", "f5"])
def test_screen_snapshot_at_operator_sizes(snap_compare, tab: str, size: tuple[int, int]) -> None:
    """Each screen at a full terminal (160 x 48) and the smallest supported one (80 x 24)."""
    assert snap_compare(_app(), press=[tab, "_"], terminal_size=size)
