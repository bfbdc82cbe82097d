"""The CNC simulator's `$` system commands and its `$$` settings, as grbl 1.1h answers them.

`SYSTEM_COMMANDS` maps each fixed command (`$`, `$$`, `$#`, `$G`, `$I`, `$N`, `$X`, `$H`) to its
handler; `$<n>=<value>` writes a setting; anything else is `error:3`. A handler returns the
lines printed before `ok`, or raises GrblError (docs/protocols/grbl.md).
"""
from __future__ import annotations

import re
from collections.abc import Awaitable, Callable
from typing import Protocol

from sims.cnc.block import NUMBER, GrblError
from sims.cnc.state import CncState
from wire.grbl_protocol import fmt, format_probe

VERSION = "1.1h"

# The `$$` listing: grbl 1.1 defaults, with axis settings for A and B as the 5-axis ports
# (grbl-Mega-5X) number them ($1x3 = A, $1x4 = B). Rates mm/min (deg/min), accel mm/s².
DEFAULT_SETTINGS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0,
    20: 0, 21: 0, 22: 0, 23: 0, 24: 25.000, 25: 500.000, 26: 250, 27: 1.000, 30: 1000, 31: 0, 32: 0,
    100: 250.000, 101: 250.000, 102: 250.000, 103: 100.000, 104: 100.000,
    110: 6000.000, 111: 6000.000, 112: 3000.000, 113: 7200.000, 114: 7200.000,
    120: 250.000, 121: 250.000, 122: 250.000, 123: 250.000, 124: 250.000,
    130: 1000.000, 131: 1000.000, 132: 500.000, 133: 360.000, 134: 360.000,
}
_INT_SETTINGS = {0, 1, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 26, 30, 31, 32}



class SystemHost(Protocol):
    """What the `$` commands use of the simulator: its machine state and the homing cycle."""

    machine: CncState
    rx_capacity: int          # the RX ring's usable bytes (its size less one)

    @property
    def state(self) -> str: ...
    async def run_homing(self) -> None: ...


SystemCommand = Callable[[SystemHost], Awaitable[list[str]]]


def _require_idle_or_alarm(sim: SystemHost) -> None:
    if sim.state not in ("Idle", "Alarm"):
        raise GrblError(8)


async def _help(sim: SystemHost) -> list[str]:
    return ["[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]"]


async def _settings(sim: SystemHost) -> list[str]:
    _require_idle_or_alarm(sim)
    return [f"${n}={int(v) if n in _INT_SETTINGS else f'{v:.3f}'}" for n, v in sim.machine.settings.items()]


async def _parameters(sim: SystemHost) -> list[str]:
    z = ",".join(fmt(0.0) for _ in range(5))
    out = [f"[{g}:{z}]" for g in ("G54", "G55", "G56", "G57", "G58", "G59", "G28", "G30", "G92")]
    out += [f"[TLO:{sim.machine.tlo:.3f}]", format_probe(sim.machine.probe_pos, sim.machine.probe_ok)]
    return out


async def _parser_state(sim: SystemHost) -> list[str]:
    return ["[GC:" + " ".join([
        sim.machine.motion_mode, "G54", "G17", "G20" if sim.machine.inches else "G21",
        "G90" if sim.machine.absolute else "G91", "G94", ("M4" if sim.machine.spindle_ccw else "M3") if sim.machine.spindle_on else "M5", "M9", "T0",
        f"F{sim.machine.feed_rate:.0f}", f"S{sim.machine.s_word:.0f}"]) + "]"]


async def _build_info(sim: SystemHost) -> list[str]:
    # the rotary letters of the configured table (XYZAB or XYZAC), as grblHAL names its own axes
    # the planner blocks and the RX ring it has (grbl 1.1h: 15,128; grblHAL 100,1024 or more)
    return [f"[VER:{VERSION}.20190825:5-axis {sim.machine.letters} (cell simulator)]",
            f"[OPT:VNM,{sim.machine.planner_blocks},{sim.rx_capacity + 1}]",
            f"[AXS:5:{sim.machine.letters}]"]


async def _startup_lines(sim: SystemHost) -> list[str]:
    return ["$N0=", "$N1="]


async def _unlock(sim: SystemHost) -> list[str]:
    _require_idle_or_alarm(sim)
    if sim.machine.alarm:
        sim.machine.alarm = False
        sim.machine.notify()
        return ["[MSG:Caution: Unlocked]"]
    return []


async def _home(sim: SystemHost) -> list[str]:
    if not sim.machine.settings[22]:
        raise GrblError(5)
    _require_idle_or_alarm(sim)
    await sim.run_homing()
    return []


SYSTEM_COMMANDS: dict[str, SystemCommand] = {
    "$": _help, "$$": _settings, "$#": _parameters, "$G": _parser_state, "$I": _build_info,
    "$N": _startup_lines, "$X": _unlock, "$H": _home,
}


def _write_setting(sim: SystemHost, number: str, value: str) -> list[str]:
    """`$<n>=<value>`."""
    _require_idle_or_alarm(sim)
    n = int(number)
    if n not in sim.machine.settings:
        raise GrblError(3)
    if not NUMBER.fullmatch(value):
        raise GrblError(2)
    v = float(value)
    if v < 0:
        raise GrblError(4)
    sim.machine.settings[n] = int(v) if n in _INT_SETTINGS else v
    return []


async def system_command(sim: SystemHost, line: str) -> list[str]:
    """One `$` line: the lines to print before `ok`; GrblError for `error:N`."""
    command = SYSTEM_COMMANDS.get(line)
    if command is not None:
        return await command(sim)
    m = re.fullmatch(r"\$(\d+)=(.*)", line)
    if m:
        return _write_setting(sim, m.group(1), m.group(2))
    raise GrblError(3)
