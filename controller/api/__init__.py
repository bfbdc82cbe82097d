"""The one way in for the CLI and the TUI (docs/architecture.md): `CellController`, the facade of a
cell session (controller/api/cell.py), and what needs no session (controller/api/offline.py)."""
from controller.api.cell import COMMANDS, CellController, preload_build_modules
from controller.api.offline import align_at, run_rows, write_run_report
from controller.api.simulated import Simulators

__all__ = ["COMMANDS", "CellController", "Simulators", "align_at", "preload_build_modules", "run_rows",
           "write_run_report"]
