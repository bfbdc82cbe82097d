"""The types the facade takes and gives, re-exported where they are defined: a typed job
(`CellJob`), a build's options and result (`BuildOptions`, `BuildResult`), a snapshot of the cell
(`Snapshot`) and its progress lines (`ProgressPrinter`), a build's trace (`Trace`), one touch of
the alignment's probe (`ProbedPoint`, what `align_at(on_point=…)` is given).

They are the facade's surface, not a way past it: a front end builds and reads these values, it
never calls the room that defines them (docs/architecture.md "One facade")."""
from controller.align.probe_cycle import ProbedPoint
from controller.job.model import CellJob
from controller.journal.trace import Trace
from controller.runtime.events import ProgressPrinter, Snapshot
from controller.runtime.work import BuildOptions, BuildResult

__all__ = ["BuildOptions", "BuildResult", "CellJob", "ProbedPoint", "ProgressPrinter", "Snapshot", "Trace"]
