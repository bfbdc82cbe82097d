"""The CNC simulator's process (laser) power output, as grbl 1.1h and grblHAL set it
(docs/laser-power.md).

`M3 S…` holds the programmed power. `M4 S…` in laser mode (`$32=1`) is grbl's dynamic power: in a
feed motion (`G1`) the output is S × the actual speed / the programmed feed, computed again as the
speed changes (grbl 1.1h stepper.c: `rpm *= current_speed * inv_rate`; grblHAL the same with
`inv_feedrate`), and off in a rapid and whenever the machine stands (grbl turns the PWM off when its
step-segment buffer runs empty). In spindle mode (`$32=0`) M4 is a spindle turning the other way:
its S as programmed.
"""
from __future__ import annotations

from sims.cnc.block import Block
from sims.cnc.state import CncState


def process_power(machine: CncState, cur: Block | None) -> float:
    """The output S now; `cur`: the motion block under way (None: the machine stands)."""
    if not machine.spindle_on:
        return 0.0
    if not (machine.spindle_ccw and int(machine.settings[32])):
        return float(machine.spindle_s)
    if cur is None or cur.verb == "G0" or cur.feed <= 0.0:
        return 0.0
    return float(machine.spindle_s) * min(max(machine.speed_mm_min, 0.0) / cur.feed, 1.0)
