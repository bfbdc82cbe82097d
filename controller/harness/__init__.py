"""The harness's public face (docs/architecture.md "One facade"): what a front end (the CLI, the
TUI) may take of the room that wires simulators in. Opening a cell (`open_cell`, `start_simulators`,
`with_urls`), the simulators in a process of their own (`SimProcess`) or served until Ctrl-C
(`serve_until_interrupted`), a seeded fault spec checked (`check_fault_spec`), the time scale a
separate `cell sim up` is fed at (`FedScale`), and the chains that open a cell of their own: the
alignment on the CNC simulator (`run_with_sim`), the repair (`repair_run_sim`, `repair_run_devices`,
and the demo's parts `make_parts`, `posed_sim`).

A front end imports these names from `controller.harness`, never from its modules (a rule in
tests/test_architecture.py). They load on first use (PEP 562 `__getattr__`): `cell sim up` does not
pay for the repair chain, nor the TUI's first paint for the simulators.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from core.lazy_names import lazy_names

if TYPE_CHECKING:   # the names as mypy sees them; at run time `__getattr__` below loads them
    from controller.harness.align_sim import run_with_sim
    from controller.harness.cell import open_cell, start_simulators, with_urls
    from controller.harness.repair import repair_run_devices, repair_run_sim
    from controller.harness.repair_parts import make_parts, posed_sim
    from controller.harness.sim import check_fault_spec
    from controller.harness.sim_clock import FedScale
    from controller.harness.sim_process import SimProcess
    from controller.harness.sim_up import serve_until_interrupted

__all__ = ["FedScale", "SimProcess", "check_fault_spec", "make_parts", "open_cell", "posed_sim", "repair_run_devices",
           "repair_run_sim", "run_with_sim", "serve_until_interrupted", "start_simulators", "with_urls"]

_WHERE = {"run_with_sim": "align_sim", "open_cell": "cell", "start_simulators": "cell", "with_urls": "cell",
          "repair_run_devices": "repair", "repair_run_sim": "repair", "make_parts": "repair_parts",
          "posed_sim": "repair_parts", "check_fault_spec": "sim", "FedScale": "sim_clock", "SimProcess": "sim_process",
          "serve_until_interrupted": "sim_up"}


__getattr__ = lazy_names(__name__, _WHERE)
