"""The CNC simulator's planner block and grbl's error: what the G-code interpreter, the `$`
commands and the executor of the simulator (sim.py) share.

`Block` is one planner entry (or a non-motion line kept in order for the execution log);
`GrblError(code)` is answered as `error:<code>` (docs/protocols/grbl.md).
"""
from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

DEVICE = "cnc"
Pos5 = tuple[float, float, float, float, float]

NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")


def pos5(p: Sequence[float]) -> Pos5:
    """The first five values of `p` (machine X Y Z and the two rotary axes) as a Pos5."""
    return (p[0], p[1], p[2], p[3], p[4])


@dataclass
class Block:
    """One planner entry, or a non-motion line kept in order for the execution log."""

    seq: int
    verb: str
    line: str
    target: Pos5 | None = None
    feed: float = 0.0                    # mm/min (rapids: the max rate)
    s: float = 0.0                       # laser / process power in effect
    spindle: bool | None = None          # M3/M4 → True, M5 → False, None: no change
    ccw: bool = False                    # M4: in laser mode the power follows the actual speed
    probe: str | None = None             # "G38.2" | "G38.3"
    started: bool = False
    done: bool = False
    contact: bool = False

    @property
    def motion(self) -> bool:
        return self.target is not None


class GrblError(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code
