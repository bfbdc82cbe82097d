"""The UI's pure parts: the braille layer preview, the job summary per role, the log filter, what is allowed."""
from __future__ import annotations

from controller.runtime.events import Snapshot
from controller.tui.log import matches
from controller.tui.widgets import braille, bounds_of
from controller.tui.session import LogRow, PlanStatus, View, job_info
from planner.job import load_job

from tests.tui.recorded import recorded_job


def test_a_horizontal_bead_is_one_row_of_dots_across_the_canvas() -> None:
    pic = braille([("x", ((0.0, 0.0), (10.0, 0.0)))], (0.0, 0.0, 10.0, 0.0), 4, 1)
    assert pic.plain == "⠤⠤⠤⠤"           # centred vertically: the third dot row of each cell


def test_the_preview_has_y_up_and_a_uniform_scale() -> None:
    # a 10 x 10 square's corner at (10, 10) is top right, (0, 0) bottom left
    paths = [("a", ((10.0, 10.0),)), ("b", ((0.0, 0.0),))]
    rows = braille(paths, (0.0, 0.0, 10.0, 10.0), 8, 4).plain.split("\n")
    assert rows == ["       ⠈", "        ", "        ", "⡀       "]  # top-right dot, bottom-left dot
    # uniform scale: a square of 8 x 4 cells (16 x 16 dots) is drawn edge to edge in both directions
    square = ((0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0), (0.0, 0.0))
    rows = braille([("s", square)], (0.0, 0.0, 10.0, 10.0), 8, 4).plain.split("\n")
    assert all(r[0] != " " and r[-1] != " " for r in rows)


def test_job_info_gives_the_process_parameters_per_role() -> None:
    info = job_info(load_job(recorded_job()), "block-slot")
    assert (info.layers, info.passes) == (3, 12)
    roles = {r.role: r for r in info.roles}
    assert [r.role for r in info.roles] == ["perimeter", "infill", "gap"]
    assert roles["perimeter"].passes == 6 and roles["perimeter"].current_a == (120.0, 122.0)
    assert roles["gap"].width_mm == 2.2 and roles["gap"].wfs_m_min == (4.6, 4.6)
    assert bounds_of(info.layer_paths) == (1.5, 1.5, 58.5, 38.5)


def test_log_filter_words_and_kind() -> None:
    door = LogRow(1, 0.0, "alarm", "fault", "door opened during the build", 1, 2)
    start = LogRow(2, 1.0, "transition", "running_wait", "ready -> running_wait on start")
    assert matches(door, "kind:alarm") and not matches(start, "kind:alarm")
    assert matches(door, "DOOR build") and not matches(door, "door estop")
    assert matches(start, "") and matches(start, "running_wait")


def test_what_the_view_allows() -> None:
    idle = Snapshot(state="idle", allowed_commands=("open_job", "estop"))
    v = View(snap=idle)
    assert v.allowed("open") and v.allowed("estop") and not v.allowed("start") and not v.allowed("plan")
    assert not v.allowed("run_alignment")                       # no touch probe on this cell
    assert View(snap=idle, can_probe=True).allowed("run_alignment")
    assert View(snap=idle, plan=PlanStatus("loaded", "part.stl")).allowed("plan")
    assert not View(snap=idle, plan=PlanStatus("loaded", "part.stl"), busy="planning").allowed("plan")
    assert not v.allowed("connect")
    assert View(snap=Snapshot(state="fault", allowed_commands=("reset", "estop"))).allowed("connect")
    running = View(snap=Snapshot(state="running_depositing", allowed_commands=("pause", "abort", "estop")),
                   can_probe=True)
    assert running.allowed("pause") and not running.allowed("run_alignment") and not running.allowed("open")


def test_apply_alignment_is_offered_once_per_job() -> None:
    """docs/contract.md §3: once the aligned job is open, `y` is no longer offered (it would move the part twice)."""
    from dataclasses import replace as _replace

    from controller.runtime.events import Snapshot

    snap = Snapshot(state="ready", allowed_commands=("open_job", "start", "estop"))
    base = View(snap=snap, job=job_info(load_job(recorded_job())), alignment={"transform": [[1, 0, 0, 0]]})
    assert base.allowed("apply_alignment")
    assert not _replace(base, alignment_applied=True).allowed("apply_alignment")


def test_after_an_estop_no_weld_value_stays_on_screen_and_the_arc_lamp_is_off() -> None:
    """Issue 19: the last bead's 152 A must not stay up after an E-stop; the lamp follows the arc-stable bit."""
    from controller.runtime.events import Snapshot
    from controller.tui.build import arc_lamp, arc_values

    welding = Snapshot(state="running_deposit", current_a=152.3, voltage_v=21.9, wfs_m_min=6.9, arc_on=True)
    assert arc_values(welding) == (152.3, 21.9, 6.9) and "ARC ON" in arc_lamp(welding)
    stopped = Snapshot(state="estop", current_a=152.3, voltage_v=21.9, wfs_m_min=6.9, arc_on=True)
    assert arc_values(stopped) == (None, None, None) and "ARC ON" not in arc_lamp(stopped)
    idle_source = Snapshot(state="running_deposit", current_a=152.3, arc_on=False)
    assert arc_values(idle_source) == (None, None, None) and "arc off" in arc_lamp(idle_source)
