"""The power-source simulator's watchdog (docs/power-source.md): the start is dropped (error 50)
after 100 ms of wall time without a new counter from the host, and only the time the simulator
itself ran counts: a stall of its own process is never the host's fault (issue 38: a TUI build
faulted on error 50 under load)."""
from __future__ import annotations

import time

from core.config import load_material
from sims.power_sim import ERR_NONE, ERR_WATCHDOG, TICK_S, WATCHDOG_S, PowerSourceSim

START = {"weld_start": True, "robot_ready": True}


def _started() -> tuple[PowerSourceSim, float]:
    sim = PowerSourceSim(load_material("inconel718-1.0mm"))
    t0 = time.monotonic()
    sim.command(START, 1, 0, 5.0, 0.0, 0.0, 1)   # the host's counter 1, now
    return sim, t0


def _ticks(sim: PowerSourceSim, t_from: float, t_to: float) -> None:
    """The simulator's own 5 ms ticks from t_from to t_to (wall, monotonic), no host frame."""
    t = t_from
    while t < t_to - 1e-9:
        t = min(t + TICK_S, t_to)
        sim.tick(t)


def test_a_host_that_stops_cycling_drops_the_start_after_the_watchdog() -> None:
    sim, t0 = _started()
    _ticks(sim, t0, t0 + WATCHDOG_S - 0.005)
    assert sim.error == ERR_NONE and sim.phase != "idle"      # 95 ms without a counter: still on
    _ticks(sim, t0 + WATCHDOG_S - 0.005, t0 + WATCHDOG_S + 0.010)
    assert sim.error == ERR_WATCHDOG and sim.phase == "idle"  # the start dropped, error 50 latched


def test_a_stall_of_the_simulator_itself_is_not_counted() -> None:
    sim, t0 = _started()
    _ticks(sim, t0, t0 + 0.060)          # the host quiet for 60 ms (its frames may be on their way)
    sim.tick(t0 + 0.060 + 0.150)         # the simulator's process did not run for 150 ms
    assert sim.self_stalls == 1
    assert sim.error == ERR_NONE, "its own 150 ms stall was counted against the host"
    # what it could have heard since: the watchdog goes on from 65 ms
    _ticks(sim, t0 + 0.210, t0 + 0.240)
    assert sim.error == ERR_NONE
    _ticks(sim, t0 + 0.240, t0 + 0.260)  # the host still silent: 105 ms of running time
    assert sim.error == ERR_WATCHDOG
