"""The CNC simulator: a 5-axis controller answering byte for byte what grbl 1.1h answers.

`CncSim` (sim.py: the serial protocol, real-time bytes, the executor loop) and `serve` (for
`cell sim up`). Its parts share one explicit state object, `CncState` (state.py), through public
fields: `gcode.py` (the interpreter), `motion.py` (a block moved over simulated time),
`system.py` (the `$` commands), `freeze.py` (the seeded freeze fault), `cut.py` (spindle and
cutters), `block.py` (the planner block and grbl's error). Protocol: docs/protocols/grbl.md.
"""
from __future__ import annotations

from sims.cnc.sim import CncSim, serve

__all__ = ["CncSim", "serve"]
