"""The one way in for the CLI and the TUI (docs/architecture.md "One facade"): `CellController`,
the facade of a cell session (controller/api/cell.py), and what needs no session, by subject:
a job (`jobs.py`), a run directory and its journal (`runs.py`), programs (`programs.py`), the
alignment's geometry (`geometry.py`), the record store (`records.py`), the stop signals and the
cell's lock (`signals.py`), the report, the runs list and an alignment off a session
(`offline.py`).

The names below are the facade's surface. They load on first use (PEP 562 `__getattr__`): a
command that needs one module of the API pays for that one (`cell plan` starts in 0.35 s), not
for the build runner's.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from core.lazy_names import lazy_names

if TYPE_CHECKING:   # the names as mypy sees them; at run time `__getattr__` below loads them
    from controller.api.cell import COMMANDS, CellController, preload_build_modules
    from controller.api.offline import (align_off_session, aligned_job, align_at, events_after, feedable_time_scale, run_rows,
                                        state_machine_doc, workpiece_probe_plan, write_run_report)
    from controller.api.simulated import Simulators
    from controller.api.types import BuildOptions, BuildResult, CellJob, ProgressPrinter, Snapshot, Trace
    from controller.api.jobs import read_job

__all__ = ["COMMANDS", "BuildOptions", "BuildResult", "CellController", "CellJob", "ProgressPrinter", "Simulators",
           "Snapshot", "Trace", "align_at", "align_off_session", "aligned_job", "events_after", "feedable_time_scale",
           "preload_build_modules", "read_job", "run_rows", "state_machine_doc", "workpiece_probe_plan",
           "write_run_report"]

_WHERE = {"COMMANDS": "cell", "CellController": "cell", "preload_build_modules": "cell",
          "aligned_job": "offline", "align_off_session": "offline", "align_at": "offline", "events_after": "offline", "run_rows": "offline",
          "workpiece_probe_plan": "offline", "write_run_report": "offline", "state_machine_doc": "offline",
          "feedable_time_scale": "offline", "Simulators": "simulated", "ProgressPrinter": "types",
          "BuildOptions": "types", "BuildResult": "types", "CellJob": "types", "Snapshot": "types", "Trace": "types",
          "read_job": "jobs"}


__getattr__ = lazy_names(__name__, _WHERE)
