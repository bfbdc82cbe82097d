"""The driver for a CNC speaking grbl 1.1 (grbl 1.1h, grblHAL): `CncLink` and what it raises and returns.

The parts share one explicit state object, `LinkState` (state.py), through its public fields:
`link.py` (CncLink: connect, commands, real-time bytes, the status poll), `receive.py` (every line
grbl prints, dispatched by kind), `stream.py` (character-counting streaming), `stop.py` (the
verified safe stop), `probe.py` (G38.x), `status.py` (lines awaiting their answer, report spans),
`results.py` (SafeStopResult, ProbeResult) and `errors.py`. Protocol: docs/protocols/grbl.md.
"""
from __future__ import annotations

from drivers.grbl.errors import (
    GrblAckLost, GrblAlarm, GrblAxesMissing, GrblError, GrblReset, GrblStopped, GrblStuck, ProbeError,
)
from drivers.grbl.link import CncLink
from drivers.grbl.results import ProbeResult, SafeStopResult
from wire.grbl_protocol import GrblStatus, StreamResult

__all__ = ["CncLink", "GrblError", "GrblAlarm", "ProbeError", "GrblReset", "GrblAckLost", "GrblStuck", "GrblStatus",
           "GrblAxesMissing", "GrblStopped", "ProbeResult", "SafeStopResult", "StreamResult"]
