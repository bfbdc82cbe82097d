"""What the grbl driver's operations return: a safe stop's verified result and a probe's touch
(records only; `errors.py` and `stop.py` both use them)."""
from __future__ import annotations

from dataclasses import dataclass, field

from wire.grbl_protocol import Pos5

__all__ = ["SafeStopResult", "ProbeResult"]


@dataclass(frozen=True)
class SafeStopResult:
    """What `CncLink.safe_stop` did and what the firmware's status reports verified.

    `verified` is True only when every check held in a report received after the last step:
    `state` Idle or Alarm, `spindle` (FS: second field) 0, `spindle_off` (accessory field says
    off), `planner_queued` and `rx_queued` 0 (from `Bf:`), `settled` (two reports at the same
    position) and `modal_m5` (`$G` shows M5). `problems` says, in words, which did not and
    `timed_out` names the bounded waits that expired ("hold", "m5", "reset", "verify", "modal")."""

    reason: str
    verified: bool
    state: str
    position: Pos5
    spindle: float
    spindle_off: bool | None
    planner_queued: int | None
    rx_queued: int | None
    settled: bool
    modal_m5: bool | None
    unanswered_lines: int          # lines of ours unanswered when the stop began (flushed by a reset)
    held: bool                     # Hold:0 reached before process off
    m5_sent: bool
    reset: bool                    # a soft reset (0x18) was sent
    alarm: int | None              # an ALARM:N raised during the stop (3: reset while moving)
    needs_unlock: bool             # state Alarm: `$X` (or `$H`) before any G-code
    needs_homing: bool             # the alarm lost the position
    hold_s: float | None           # call → Hold:0 (or standing) seen
    spindle_off_s: float | None    # call → first report showing spindle 0 with the accessory off
    elapsed_s: float               # call → everything verified (or given up)
    timed_out: tuple[str, ...] = ()
    problems: tuple[str, ...] = ()
    steps: tuple[str, ...] = field(default=())

    def summary(self) -> str:
        """One line for an error message or the journal."""
        how = "reset" if self.reset else ("M5" if self.m5_sent else "no action")
        lock = "; needs $H (position lost)" if self.needs_homing else ("; needs $X" if self.needs_unlock else "")
        head = "safe stop verified" if self.verified else "safe stop NOT verified (" + "; ".join(self.problems) + ")"
        return (f"{head}: {how}, state {self.state}, spindle {self.spindle:g}, "
                f"queued {self.planner_queued} block(s) / {self.rx_queued} byte(s), {self.elapsed_s:.2f} s{lock}")


@dataclass(frozen=True)
class ProbeResult:
    """Where the probe tripped (machine coordinates x, y, z, a, b) and whether it touched."""

    position: Pos5
    contact: bool
