"""The demo's figures and the in-process simulators' reply timeout, shared by the CLI, the TUI and bench."""
from __future__ import annotations

import os

from core.config import CONFIG_DIR
from core.errors import InputError

DEMO_PART = CONFIG_DIR / "parts" / "square-hole.stl"
DEMO_WIDTH_MM = 7.0          # Inconel 718 bead; 39 layers of 0.77 mm for the 30 mm part
DEMO_TIME_SCALE = 60.0       # ~64 min of build in about a minute; at 120 the host could not keep the robot fed
                             # (travel speed 18-49 % off on loaded runs; 0.3 % at 60)
DEMO_MAX_STEP_MM = 6.0       # split only long demo segments (the planner's own points are 1.7 mm apart, median)
# The one bus reply timeout with in-process simulators (the CLI, the TUI, the harness, the tests and
# bench/ all use it): they share the GIL with the controller, and on a loaded host 250 ms tripped
# lost links that were only a busy interpreter. Real devices keep cell.yaml's timeouts.
SIM_REPLY_TIMEOUT_MS = 500.0


def sim_reply_timeout_ms() -> float:
    """Bus reply timeout with in-process simulators; CELL_SIM_REPLY_TIMEOUT_MS overrides it
    (a heavily loaded test machine, where the simulators and the UI share one interpreter)."""
    raw = os.environ.get("CELL_SIM_REPLY_TIMEOUT_MS")
    if raw is None:
        return SIM_REPLY_TIMEOUT_MS
    try:
        value = float(raw)
    except ValueError:
        raise InputError(f"CELL_SIM_REPLY_TIMEOUT_MS={raw!r} is not a number of milliseconds") from None
    if value <= 0:
        raise InputError(f"CELL_SIM_REPLY_TIMEOUT_MS={raw!r} must be positive")
    return value
