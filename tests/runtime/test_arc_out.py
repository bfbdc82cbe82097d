"""Where a crashed bead's arc went out (controller/runtime/arc_out.py) and what the journal keeps for it."""
from __future__ import annotations

import json
import math
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from controller.runtime.arc_out import RunOn, arc_lengths, arc_out_lower_bound, point_at, project
from controller.job.weld_path import weld_points
from controller.journal.store import Journal

SQUARE = [(0.0, 0.0, 1.0), (30.0, 0.0, 1.0), (30.0, 30.0, 1.0), (0.0, 30.0, 1.0), (0.0, 0.5, 1.0)]


def test_the_run_on_estimate_follows_the_watchdog_speed_and_time_scale() -> None:
    ro = RunOn()  # 100 ms watchdog (wall), no burn-back after it, 20 ms slack, 0.1 mm margin
    # 600 mm/min at time scale 1: 10 mm/s for 0.08 s -> 0.8 mm, less the margin
    assert math.isclose(arc_out_lower_bound(10.0, 600, 1.0, ro, 50.0, 100.0), 10.7)
    # time scale 10: the watchdog stays wall time, the torch runs 10x faster
    assert math.isclose(arc_out_lower_bound(10.0, 600, 10.0, ro, 500.0, 1000.0), 17.9)
    # the robot stopped first (its queue ran out): the arc went out where it stood
    assert math.isclose(arc_out_lower_bound(10.0, 600, 1.0, ro, 10.5, 100.0), 10.499)
    # the robot stopped on the last point with the arc on: the bead is complete
    assert arc_out_lower_bound(99.5, 600, 1.0, ro, 100.0, 100.0) == 100.0
    # no robot position (another platform, or off the path): no estimate, never behind what is known
    assert arc_out_lower_bound(10.0, 600, 1.0, ro, None, 100.0) == 10.0
    assert arc_out_lower_bound(10.0, 600, 1.0, ro, 9.0, 100.0) == 10.0
    # a source that burns back after its watchdog: process time, never under 2 bus cycles of wall
    rb = RunOn(burnback_s=0.08)
    assert math.isclose(rb.wall_s(1.0), 0.16) and math.isclose(rb.wall_s(10.0), 0.10)
    # device properties come from cell.yaml's power source section (ms there)
    dev = type("Dev", (), {"watchdog_ms": 250.0, "watchdog_burnback_s": 0.2})()
    r2 = RunOn.from_device(dev)
    assert (r2.watchdog_s, r2.burnback_s) == (0.25, 0.2)


def test_positions_along_a_pass() -> None:
    pts = weld_points(SQUARE, 1.0)
    cum = arc_lengths(pts)
    assert math.isclose(cum[-1], 30 + 30 + 30 + 29.5)
    k, p = point_at(pts, cum, 30.25)
    assert k == 30 and math.dist(p, (30.0, 0.25, 1.0)) < 1e-9
    k, p = point_at(pts, cum, 12.0)
    assert k == 12 and p == pts[12]
    assert math.isclose(project(pts, cum, (30.0, 0.25, 1.0), 10.0), 30.25)
    # the closed square comes back near its start: the search runs forward from what is known
    assert math.isclose(project(pts, cum, (0.0, 0.5, 1.0), 100.0), cum[-1])
    assert project(pts, cum, (15.0, 15.0, 1.0), 0.0) is None  # off the path


@settings(max_examples=300, deadline=None)
@given(kill=st.floats(0.0, 1.0), step=st.sampled_from([0.5, 1.0, 2.0]), speed=st.sampled_from([300.0, 600.0, 1366.5]),
       scale=st.sampled_from([1.0, 4.0, 20.0]), cycle_phase=st.floats(0.0, 0.020), tick=st.floats(0.0, 0.010))
def test_the_estimate_never_leaves_a_gap_and_overlaps_by_about_one_move(kill: float, step: float, speed: float,
                                                                         scale: float, cycle_phase: float,
                                                                         tick: float) -> None:
    """A timeline like the simulators': the robot moves at constant speed and reports each move's
    end; the controller dies at `kill` within a move and its last counter reached the source up to
    a cycle before; the start drops 100 ms after it (+ up to one 5 ms tick) and the arc goes out."""
    ro = RunOn()
    v = speed / 60.0 * scale                      # mm per wall second
    move_s = step / v
    t_kill = 10.0 + kill * move_s                 # the last journaled EXE: move 10 s / move_s ended at 10.0 s
    s_known = v * 10.0
    t_counter = t_kill - cycle_phase
    t_out = t_counter + ro.watchdog_s + tick / 2
    s_out = v * t_out
    est = arc_out_lower_bound(s_known, speed, scale, ro, s_robot=s_out + 5 * step, s_end=1e9)
    assert est <= s_out                           # nothing missing
    assert s_out - est <= step + v * (ro.timing_slack_s + 0.010) + ro.margin_mm + 1e-9


def test_the_journal_keeps_the_re_arc_point_and_arc_losses(tmp_path: Path) -> None:
    j = Journal(tmp_path / "j.sqlite")
    j.event("run", json.dumps({"run": j.run, "time_scale": 7.5, "passes_left": 2}))
    j.pass_state(0, 0, "started", start_idx=0, points=10, start_mm=0.0)
    j.pass_state(0, 0, "arc_on", idx=0, start_mm=0.0)
    j.close()
    j = Journal(tmp_path / "j.sqlite")        # the resume: run 2
    r = j.pass_resume(0, 0)
    assert (r.state, r.run, r.start_mm, r.arc_run, r.arc_unstable) == ("arc_on", 1, 0.0, 1, False)
    assert j.run_time_scale(1) == 7.5 and j.run_time_scale(2) is None
    j.pass_state(0, 0, "started", start_idx=3, points=10, start_mm=3.4)
    j.pass_state(0, 0, "arc_on", idx=3, start_mm=3.4)
    j.event("arc", "arc unstable while depositing", layer=0, pass_=0)
    r = j.pass_resume(0, 0)
    assert (r.state, r.run, r.start_mm, r.arc_run, r.arc_unstable) == ("arc_on", 2, 3.4, 2, True)
    assert j.pass_resume(0, 1) is None
    j.close()
