"""The power-source simulator's parameters: link and phase timing, error numbers, the synergic
line, the process-phase durations and the host command it holds (sims/power_sim.py).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TypedDict

from wire.power_registers import COMMAND_BITS

WATCHDOG_S = 0.100          # start dropped after this long without a new counter (wall)
ARC_HOLD_S = 0.016          # arc stable held this long before motion release (wall)
MIN_PHASE_WALL_S = 0.020    # a scaled process phase never lasts less than 2 bus cycles
TICK_S = 0.005              # model update period when no host cycle comes

SELF_STALL_S = 0.030   # a tick this late (they come every 5 ms): the simulator itself stalled
ERR_NONE, ERR_GAS, ERR_WIRE_OUT, ERR_WIRE_STICK, ERR_WATCHDOG, ERR_COLLISION = 0, 10, 20, 30, 50, 60
ERROR_TEXT = {ERR_GAS: "gas fault", ERR_WIRE_OUT: "wire out", ERR_WIRE_STICK: "wire stick",
              ERR_WATCHDOG: "watchdog: no new counter for 100 ms", ERR_COLLISION: "torch collision"}


@dataclass(frozen=True)
class SynergicLine:
    """Voltage U = u0 + k·WFS + trim_v·arc_trim (V); current from WFS on the material's line."""

    u0_v: float = 13.5
    v_per_m_min: float = 1.2
    v_per_trim: float = 0.3       # per unit of arc-length trim (±10 -> ±3 V)
    noise: float = 0.005          # relative 1σ ripple of the actuals


@dataclass(frozen=True)
class ProcessTimes:
    """Process-phase durations in process (simulated) seconds."""

    preflow_s: float = 0.10
    ignition_s: float = 0.05      # pre-flow end -> current flow
    stabilise_s: float = 0.03     # current flow -> arc stable
    burnback_s: float = 0.08
    postflow_s: float = 0.50


DEFAULT_LINE = SynergicLine()     # PowerSourceSim's defaults (frozen: shared safely)
DEFAULT_TIMES = ProcessTimes()


@dataclass
class HostCommand:
    """One host cycle's command as the model took it (the command registers or WELD_CMD, decoded)."""

    bits: dict[str, bool] = field(default_factory=lambda: {k: False for k in COMMAND_BITS})
    mode: int = 0
    job: int = 0
    wfs: float = 0.0
    arc_trim: float = 0.0
    dynamic_trim: float = 0.0
    counter: int = -1


class PowerStatus(TypedDict):
    """What the source reports each cycle (`PowerSourceSim.status`), on Modbus and on CAN."""

    echo: int
    bits: dict[str, bool]
    error: int
    voltage: float
    current: float
    wfs: float
