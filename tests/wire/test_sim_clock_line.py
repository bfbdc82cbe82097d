"""The simulators' clock line carries an injected fault (wire/sim_clock.py, INJECT; sims/inject.py)."""
from __future__ import annotations

import time

import pytest

from sims.cellio_sim import CellIOSim
from sims.clock import SimClock
from sims.inject import inject
from wire.sim_clock import Inject, parse_ok, parse_request


def test_an_inject_line_reads_back_as_the_same_request() -> None:
    req = Inject("cellio", "door_open", 0.5)
    assert parse_request(req.line()) == req
    assert parse_request(b"INJECT power_source arc_loss\n") == Inject("power_source", "arc_loss", None)
    assert "INJECT <device> <fault>" in str(parse_request(b"INJECT cellio\n"))
    assert "not a number" in str(parse_request(b"INJECT cellio door_open soon\n"))
    with pytest.raises(ValueError, match="takes door_open"):
        parse_ok(b"ERR the cell I/O takes door_open, door_close, estop, estop_release, not 'flood'\n")


def test_the_door_opens_for_the_given_wall_time_at_any_time_scale() -> None:
    clock = SimClock(600.0)
    io = CellIOSim(clock=clock)
    sims: dict[str, object] = {"cellio": io}
    inject(sims, "cellio", "door_open", 0.2)
    io.tick()
    assert io.inputs["door_closed"] is False
    time.sleep(0.25)
    io.tick()
    assert io.inputs["door_closed"] is True            # 0.2 wall seconds = 120 simulated ones at 600x
    inject(sims, "cellio", "estop")
    io.tick()
    assert io.inputs["estop_released"] is False
    with pytest.raises(ValueError, match="no simulated robot"):
        inject(sims, "robot", "freeze")
