"""Operator commands and the remaining interlocks during a build: pause/resume/abort at the end
of a bead, E-stop (reset only once released), a lost robot link; snapshots for the views."""
from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from bench._coverage import coverage, read_segments
from controller.job.read import job_from_dict
from controller.runtime.machine import TransitionRefused
from tests.cells import Cell, planned, small_job

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


async def test_pause_waits_for_the_end_of_the_bead_then_resume_and_abort(tmp_path: Path) -> None:
    job = small_job(n_layers=3)
    async with Cell(tmp_path, scale=10) as c:
        c.ctl.open_job(job_from_dict(job))
        snaps: list = []
        c.ctl.subscribe(snaps.append)
        assert c.ctl.allowed_commands() == ["open_job", "run_alignment", "start", "estop"]
        build = asyncio.ensure_future(c.ctl.start())
        await c.wait_for(lambda s: s.state == "running_depositing" and s.layer == 0 and s.pass_ == 0)
        assert {"pause", "abort", "estop"} <= set(c.ctl.allowed_commands()) and "start" not in c.ctl.allowed_commands()
        c.ctl.pause()
        assert c.ctl.snapshot().state == "running_depositing"  # the bead goes on
        await c.wait_for(lambda s: s.state == "paused")
        assert c.ctl.snapshot().passes_done == 1 and c.ctl.allowed_commands() == ["resume", "abort", "estop"]
        with pytest.raises(TransitionRefused):
            c.ctl.pause()
        c.ctl.resume()
        await c.wait_for(lambda s: s.state == "running_depositing" and s.layer == 1)
        c.ctl.abort()
        res = await asyncio.wait_for(build, 20)
        links = {ls.device: ls for ls in c.ctl.snapshot().links}
    assert res.state == "aborted" and res.passes_done in (3, 4)
    # nothing deposited twice and every bead that was started was finished
    cov = coverage(planned(job)[: res.passes_done], read_segments(c.log / "deposit.jsonl"))
    assert cov.missing_mm < 0.05 and cov.excess_mm < 0.05
    states = [s.state for s in snaps]
    assert states.index("paused") < states.index("aborted")
    assert max(s.passes_done for s in snaps) == res.passes_done and any(s.current_a for s in snaps)
    assert links["robot"].frames_tx > 50 and links["power_source"].frames_tx > 50 and links["cellio"].connected


async def test_estop_latches_until_the_input_is_released_and_reset(tmp_path: Path) -> None:
    job = small_job(n_layers=2)
    async with Cell(tmp_path, scale=5) as c:
        c.ctl.open_job(job_from_dict(job))
        build = asyncio.ensure_future(c.ctl.start())
        await c.wait_for(lambda s: s.state == "running_depositing" and s.pass_ == 1)
        io = c.harness.sim("cellio")
        c.harness.call(io.press_estop)
        res = await asyncio.wait_for(build, 10)
        assert res.state == "estop" and c.ctl.allowed_commands() == ["reset"]
        await asyncio.sleep(0.05)
        with pytest.raises(TransitionRefused, match="E-stop is still pressed"):
            await c.ctl.reset()
        c.harness.call(io.release_estop)
        await asyncio.sleep(0.1)
        await c.ctl.reset()
        res = await c.ctl.start()
    assert res.state == "complete" and res.passes_done == 4
    cov = coverage(planned(job), read_segments(c.log / "deposit.jsonl"))
    assert cov.missing_mm < 0.05 and cov.excess_mm < 2.0, cov.as_dict()


async def test_a_lost_robot_link_latches_a_fault(tmp_path: Path) -> None:
    async with Cell(tmp_path, scale=5) as c:
        c.ctl.open_job(job_from_dict(small_job(n_layers=2)))
        build = asyncio.ensure_future(c.ctl.start())
        await c.wait_for(lambda s: s.state == "running_depositing")
        c.harness.call(c.harness.sim("robot").server.unplug, 1.0)
        res = await asyncio.wait_for(build, 10)
        assert res.state == "fault"
        assert "link lost" in c.ctl.interlocks.trips[0].message
        # weld start went down with it
        await asyncio.sleep(0.05)
        assert c.ctl.devices.power.status.command.weld_start is False
