"""The operator UI driven with Textual's Pilot against the simulators (`cell tui --sim`).

Main flow: a dimmed command is refused with the controller's message, open the demo part,
plan it, start, pause, resume, the door opens (fault, alarm on screen), close it, reset.
Quitting mid-build asks first and stops the arc through the facade; the journal stays.
"""
from __future__ import annotations

import asyncio
import json
import sqlite3
import time
from pathlib import Path

import pytest
from textual.events import Key
from textual.widgets import Button, Input

from controller.harness.cell import start_simulators, with_urls
from controller.tui.app import CellApp, ConfirmQuit, OpenDialog
from controller.tui.start_dialog import StartDialog
from controller.tui.session import CellSession
from core.config import load_cell, load_sim

pytestmark = [pytest.mark.timeout(180), pytest.mark.realtime]
SIZE = (120, 36)
TIME_SCALE = 600.0   # process time 600x: interpass cooling takes a fraction of a second


@pytest.fixture(autouse=True)
def _tolerant_bus_timeout(monkeypatch: pytest.MonkeyPatch) -> None:
    """The UI, the controller and every simulator share one interpreter here, next to another
    test worker on 2 cores: a 250 ms GIL stall during probing is a test-machine artefact, not a
    lost link. Link loss itself is tested against the drivers and in test_a_link_that_drops."""
    monkeypatch.setenv("CELL_SIM_REPLY_TIMEOUT_MS", "1000")


async def until(pilot, cond, timeout: float, what: str) -> None:  # type: ignore[no-untyped-def]
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout:
            app = pilot.app
            raise AssertionError(f"timed out waiting for {what}: state {app.view.snap.state}, "
                                 f"message {app.last_message!r}, alarms {app.view.snap.alarms}")
        await pilot.pause(0.1)


async def press(pilot, *keys: str) -> None:  # type: ignore[no-untyped-def]
    """Key presses as the terminal driver posts them.

    (Pilot.press then waits for the whole process to go idle, which never happens while the
    simulators and the controller run in it: a second per key for nothing.)
    """
    for k in keys:
        pilot.app.post_message(Key(k, k if len(k) == 1 else None))
        await pilot.pause(0.05)


async def click(pilot, selector: str) -> None:  # type: ignore[no-untyped-def]
    await until(pilot, lambda: bool(pilot.app.screen.query(selector)), 5, f"{selector} on screen")
    pilot.app.screen.query_one(selector, Button).press()
    await pilot.pause(0.05)


def footer_keys(app: CellApp) -> dict[str, bool]:
    """Command keys shown in the footer -> enabled (False: shown dimmed)."""
    out = {}
    for key, ab in app.screen.active_bindings.items():
        if ab.binding.show and ab.binding.action.startswith("cmd("):
            out[key] = ab.enabled
    return out


def state(app: CellApp) -> str:
    return app.view.snap.state


async def test_main_flow_against_the_simulators(tmp_path: Path) -> None:
    # The simulators in `cell sim up` beside this process, as `cell tui --sim` runs them: in this
    # interpreter they would take the interpreter lock from the controller's device cycles
    # (docs/testing.md, "A loop that never blocks"); the door opens over their clock line.
    cfg, sims = await start_simulators(with_urls(load_cell(), {}, time_scale=TIME_SCALE), True, process=True,
                                       log_dir=tmp_path / "sim")
    assert sims is not None
    session = CellSession(cfg, sim_cfg=load_sim(), runs_dir=tmp_path / "runs", sims_beside=True)
    app = CellApp(session)
    try:
        async with app.run_test(size=SIZE) as pilot:
            await until(pilot, lambda: state(app) == "idle", 30, "the simulators to connect")
            keys = footer_keys(app)
            assert keys["o"] is True and keys["s"] is False and keys["p"] is False and keys["e"] is True

            # A dimmed command is still sent and refused with the controller's own message.
            await press(pilot, "p")
            await until(pilot, lambda: "refused" in app.last_message, 5, "the refusal")
            assert "'pause' is not allowed in state idle" in app.last_message

            # Open the demo part (the dialog offers it) and plan it: progress, then the job is open.
            await press(pilot, "o")
            await until(pilot, lambda: isinstance(app.screen, OpenDialog) and app.screen.query("#open-path"), 5,
                        "the open dialog")
            assert app.screen.query_one("#open-path").value.endswith("square-hole.stl")
            await press(pilot, "enter")
            await until(pilot, lambda: app.view.plan.state == "loaded", 5, "the part to load")
            await press(pilot, "g")
            await until(pilot, lambda: state(app) == "ready" and app.view.job is not None, 60, "planning")
            job = app.view.job
            assert job.layers == app.view.plan.total > 10 and job.passes == app.view.snap.passes_total
            summary = str(app.query_one("#job-summary").render())
            assert f"layers          {job.layers}" in summary and "perimeter" in [r.role for r in job.roles]

            # Probe and align the substrate on the CNC (touches listed as they arrive), apply the
            # transform: the job re-opens moved by it.
            await press(pilot, "f2", "l")
            await until(pilot, lambda: app.view.alignment is not None and not app.view.busy, 60, "the alignment")
            await pilot.pause(0.3)
            planes = app.query_one("#align-planes")
            assert [str(planes.get_row_at(i)[0]) for i in range(planes.row_count)][:2] == ["top", "side"]
            assert abs(app.view.alignment["face_angle_deg"]) > 0.5        # sim.yaml turns the part 1.5°
            assert "leveling" in str(app.query_one("#align-result").render())
            await press(pilot, "y")
            await until(pilot, lambda: (app.view.snap.job_name or "").endswith("-aligned"), 15, "the aligned job")
            await until(pilot, lambda: state(app) == "ready", 5, "ready")

            # Start on the Build screen: cell.yaml gives no wire lot, gas or operator, so the start
            # dialog asks for them; they show on the banner and go into the journal (docs/records.md).
            await press(pilot, "f3", "s")
            await until(pilot, lambda: isinstance(app.screen, StartDialog) and app.screen.query("#start-wire-lot"), 5,
                        "the start dialog")
            app.screen.query_one("#start-wire-lot", Input).value = "LOT-4711"
            app.screen.query_one("#start-operator", Input).value = "A. Welder"
            await click(pilot, "#start-ok")
            await until(pilot, lambda: state(app).startswith("running_"), 15, "the build to start")
            await pilot.pause(0.3)
            banner = str(app.query_one("#build-state").render())
            assert "lot LOT-4711" in banner and "operator A. Welder" in banner
            # pause (at the end of a bead), resume
            await press(pilot, "p")
            await until(pilot, lambda: state(app) == "paused", 30, "the pause at the end of a bead")
            keys = footer_keys(app)
            assert keys["r"] is True and keys["p"] is False and keys["a"] is True
            banner = str(app.query_one("#build-state").render())
            assert "PAUSED" in banner
            done_at_pause = app.view.snap.passes_done
            # Keys of steps that do not apply now are refused too, never acted on (no reconnect
            # under a build, no other job).
            await press(pilot, "c")
            await until(pilot, lambda: "'connect' is not allowed in state paused" in app.last_message, 5, "refusal")
            await press(pilot, "o")
            await until(pilot, lambda: "'open' is not allowed in state paused" in app.last_message, 5, "refusal")
            assert not isinstance(app.screen, OpenDialog) and state(app) == "paused"
            await press(pilot, "r")
            await until(pilot, lambda: state(app).startswith("running_"), 10, "the resume")
            await until(pilot, lambda: app.view.snap.passes_done > done_at_pause, 30, "a bead after the resume")

            # The door opens mid-build: the interlock latches a fault, the alarm is on screen.
            sims.inject("cellio", "door_open")
            await until(pilot, lambda: state(app) == "fault", 10, "the door interlock")
            await pilot.pause(0.3)
            alarms = str(app.query_one("#build-alarms").render())
            assert "door" in alarms
            assert footer_keys(app)["x"] is True and footer_keys(app)["s"] is False
            sims.inject("cellio", "door_close")
            await press(pilot, "x")
            await until(pilot, lambda: state(app) == "idle", 15, "the reset")
            assert app.view.snap.passes_done >= done_at_pause + 1

            # The journal's events are on the Log screen, filterable.
            await press(pilot, "f4")
            await until(pilot, lambda: any("door" in r.message for r in app.query_one("LogPane").rows), 5, "the log")
            app.set_focus(app.query_one("#log-filter", Input))
            await press(pilot, *"kind:alarm")
            await pilot.pause(0.2)
            table = app.query_one("#log-table")
            shown = [str(table.get_row_at(i)[-1]) for i in range(table.row_count)]
            assert shown and any("door" in m for m in shown)
            assert all(str(table.get_row_at(i)[1]).find("alarm") >= 0 for i in range(table.row_count))
    finally:
        session.close()
        sims.stop()


async def test_quit_during_a_build_asks_and_stops_the_arc(tmp_path: Path) -> None:
    from tests.tui.recorded import recorded_job

    job_file = tmp_path / "block.json"
    job_file.write_text(json.dumps(recorded_job()))
    # the simulators in `cell sim up` beside this process, as `cell tui --sim` runs them (a build in
    # one interpreter with them is not the product's topology: docs/testing.md, "A loop that never blocks")
    cfg, sims = await start_simulators(with_urls(load_cell(), {}, time_scale=10.0), True, process=True,  # beads of seconds
                                       log_dir=tmp_path / "sim")
    assert sims is not None
    session = CellSession(cfg, sim_cfg=load_sim(), runs_dir=tmp_path / "runs", sims_beside=True)
    try:
        await _quit_mid_build(session, job_file)
    finally:
        session.close()
        sims.stop()


async def _quit_mid_build(session: CellSession, job_file: Path) -> None:
    app = CellApp(session)
    async with app.run_test(size=SIZE) as pilot:
        await until(pilot, lambda: state(app) == "idle", 30, "the simulators to connect")
        await press(pilot, "o")
        await until(pilot, lambda: isinstance(app.screen, OpenDialog) and app.screen.query("#open-path"), 5,
                    "the open dialog")
        app.screen.query_one("#open-path").value = str(job_file)
        await click(pilot, "#open-ok")
        await until(pilot, lambda: state(app) == "ready", 15, "the job to open")
        await press(pilot, "s")
        await until(pilot, lambda: isinstance(app.screen, StartDialog), 5, "the start dialog")
        await click(pilot, "#start-ok")   # nothing given: the build starts untraced (cell.yaml requires no lot)
        await until(pilot, lambda: state(app) == "running_depositing", 20, "an arc")
        # Quit (Textual's Ctrl+Q as well as q) asks first; "Stay" leaves the build running.
        await press(pilot, "ctrl+q")
        await until(pilot, lambda: isinstance(app.screen, ConfirmQuit), 5, "the confirmation")
        await click(pilot, "#quit-no")
        await pilot.pause(0.3)
        assert not isinstance(app.screen, ConfirmQuit) and state(app).startswith("running_")
        await press(pilot, "q")
        await until(pilot, lambda: isinstance(app.screen, ConfirmQuit), 5, "the confirmation")
        run_dir = Path(app.view.snap.run_dir)
        await click(pilot, "#quit-yes")
        t0 = time.monotonic()
        while app.is_running and time.monotonic() - t0 < 20:
            await asyncio.sleep(0.1)
        assert not app.is_running
    # The arc went off through the facade (software E-stop: weld start dropped, motion held),
    # and the journal keeps the build for `cell resume`.
    assert session.ctl.machine.state.value == "estop"
    db = sqlite3.connect(run_dir / "journal.sqlite")
    events = [m for (m,) in db.execute("SELECT message FROM events")]
    assert any("software E-stop" in m for m in events)
    # the bead under the arc at the stop is journaled as interrupted: that is where `cell resume` re-arcs
    assert db.execute("SELECT count(*) FROM passes WHERE state = 'interrupted'").fetchone()[0] == 1
    assert db.execute("SELECT count(*) FROM progress").fetchone()[0] > 0
    db.close()


async def test_a_link_that_drops_and_comes_back(tmp_path: Path) -> None:
    """The cell I/O stops answering: fault, the Devices screen names it; it answers again: reconnect."""
    session = CellSession(sim=True, runs_dir=tmp_path / "runs", time_scale=TIME_SCALE)
    app = CellApp(session)
    try:
        async with app.run_test(size=SIZE) as pilot:
            await until(pilot, lambda: state(app) == "idle", 30, "the simulators to connect")
            assert "c" not in footer_keys(app)           # Connect is hidden while connected
            session.harness.sim("cellio").silence(1.5)
            await until(pilot, lambda: state(app) == "fault", 10, "the link loss")
            await press(pilot, "f5")
            await until(pilot, lambda: any(d.device == "cellio" and d.last_error for d in app.view.devices), 5,
                        "the device's last error")
            await pilot.pause(0.3)
            table = app.query_one("#dev-table")
            rows = [table.get_row_at(i) for i in range(table.row_count)]
            assert any(row[0] == "cellio" and "cell I/O" in str(row[-1]) for row in rows)
            assert footer_keys(app)["c"] is True
            await pilot.pause(1.5)                       # the coupler answers again
            await press(pilot, "c")
            await until(pilot, lambda: state(app) == "idle" and not app.view.busy, 20, "the reconnect")
            assert all(d.connected for d in app.view.devices)
            cellio = next(d for d in app.view.devices if d.device == "cellio")
            assert cellio.last_error and "cell I/O" in cellio.last_error   # the last error stays visible
            assert "c" not in footer_keys(app)
    finally:
        session.close()
