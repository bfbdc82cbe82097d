"""SIGINT, SIGTERM and SIGHUP for a command's life (controller/runtime/stops.py): recorded until
a loop attaches, then the first one stops the controller on its fault path (`attach(ctl)`) or
cancels the command's task before a build; `exit_code()` 130 / 143 / 129."""
from controller.runtime.stops import SignalStop, Stoppable, StopSignals, attach, current, detach, installed

__all__ = ["SignalStop", "StopSignals", "Stoppable", "attach", "current", "detach", "installed"]
