"""The one way in for the CLI and the TUI (docs/architecture.md): `CellController`, the facade of a
cell session (controller/api/cell.py), what needs no session (controller/api/offline.py), and the
types they take and give (a job, a snapshot, a build's trace)."""
from controller.api.cell import COMMANDS, CellController, preload_build_modules
from controller.api.offline import aligned_job, align_at, events_after, run_rows, workpiece_probe_plan, write_run_report
from controller.api.simulated import Simulators
from controller.job.model import CellJob
from controller.job.read import read_job
from controller.journal.trace import Trace
from controller.runtime.events import Snapshot

__all__ = ["COMMANDS", "CellController", "CellJob", "Simulators", "Snapshot", "Trace", "align_at", "aligned_job",
           "events_after", "preload_build_modules", "read_job", "run_rows", "workpiece_probe_plan",
           "write_run_report"]
