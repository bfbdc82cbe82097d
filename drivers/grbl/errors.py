"""The exceptions of the grbl driver (drivers/grbl/).

Every one is a DeviceError (core: the device refused a command or reported a fault) whose
message names the controller's URL."""
from __future__ import annotations

from drivers.errors import DeviceError
from drivers.grbl.results import SafeStopResult
from wire.grbl_protocol import alarm_meaning, error_meaning

__all__ = ["GrblError", "GrblAlarm", "ProbeError", "GrblAckLost", "GrblStuck", "GrblReset", "GrblAxesMissing",
           "GrblStopped"]


class GrblError(DeviceError):
    """grbl refused a line with `error:N`: `code`, `meaning`, the `line` text and, when
    streaming, its 1-based `line_number` in the streamed input. A stream stopped by it ran the
    driver's safe stop first: `safe_stop` holds what that verified (None outside a stream)."""

    def __init__(self, code: int, line: str, line_number: int | None = None, url: str = "",
                 safe_stop: SafeStopResult | None = None) -> None:
        self.code = code
        self.meaning = error_meaning(code)
        self.line = line
        self.line_number = line_number
        self.safe_stop = safe_stop
        where = f"line {line_number} " if line_number is not None else ""
        note = f"; {safe_stop.summary()}" if safe_stop is not None else ""
        super().__init__(f"cnc{' at ' + url if url else ''}: {where}{line!r} refused with error:{code} "
                         f"({self.meaning}){note}")


class GrblAlarm(DeviceError):
    """grbl raised `ALARM:N` (the machine is locked: `$X` unlock or `$H` home to go on)."""

    def __init__(self, code: int, line: str | None = None, url: str = "", detail: str = "") -> None:
        self.code = code
        self.meaning = alarm_meaning(code)
        self.line = line
        on = f" during {line!r}" if line else ""
        super().__init__(f"cnc{' at ' + url if url else ''}: ALARM:{code}{on} ({self.meaning}){detail}")


class ProbeError(GrblAlarm):
    """A probe cycle failed: ALARM:4 (probe already tripped) or ALARM:5 (no contact within travel)."""


class GrblAckLost(DeviceError):
    """grbl sits idle while lines are still unacknowledged: their `ok` was lost on the line."""


class GrblStuck(DeviceError):
    """grbl keeps reporting Idle but does not read the lines waiting in its RX buffer."""


class GrblReset(DeviceError):
    """The controller was reset (0x18 or power cycle) while lines were still unacknowledged."""


class GrblAxesMissing(DeviceError):
    """A job (or an alignment) needs axes the controller does not have: `firmware`, `have`
    (the axis letters it reports) and `missing` (the letters it lacks)."""

    def __init__(self, message: str, firmware: str, have: str, missing: str) -> None:
        self.firmware = firmware
        self.have = have
        self.missing = missing
        super().__init__(message)


class GrblStopped(DeviceError):
    """A stream (or command) ended because `CncLink.safe_stop(reason)` stopped the machine;
    `result` is what the safe stop verified."""

    def __init__(self, message: str, result: SafeStopResult) -> None:
        self.result = result
        super().__init__(message)
