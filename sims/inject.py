"""A seeded fault now, by the device's simulator: the one dispatch of `Simulators.inject`, in this
process (controller/harness/sim.py) and in `cell sim up` over its clock line (wire/sim_clock.py).

The power source takes its faults (sims/power_sim.py: arc_loss, ignition_fail, ...); the cell
I/O takes the operator's actions on the door and the E-stop (sims/cellio_sim.py).
"""
from __future__ import annotations

from sims.cellio_sim import CellIOSim
from sims.power_sim import PowerSourceSim


def inject(sims: dict[str, object], device: str, fault: str, duration_s: float | None = None) -> None:
    """`fault` now on `device`'s simulator; ValueError naming what it takes otherwise."""
    target = sims.get(device)
    if isinstance(target, PowerSourceSim):
        target.inject(fault, duration_s=duration_s)
    elif isinstance(target, CellIOSim):
        target.inject(fault, duration_s=duration_s)
    elif target is None:
        raise ValueError(f"no simulated {device} here (simulated: {', '.join(sorted(sims)) or 'none'})")
    else:
        raise ValueError(f"the simulated {device} takes no seeded fault; faults go to the power source "
                         "and the cell I/O (door, E-stop)")
