"""What every simulator's `serve(ctx)` gets and returns (`cell sim up`, sims/up.py): `SimContext`,
`Served`, and `attach`, which gives the shared World its process physics once.

A leaf of the simulators: it imports the World and the physics, never a simulator module, so
each simulator may import it.
"""
from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path

from core.config import CellConfig, SimConfig, load_material
from sims.clock import SimClock
from sims.faults import parse_fault_spec
from sims.process_world import ProcessPhysics
from sims.world import World

__all__ = ["SimContext", "Served", "attach"]


@dataclass
class SimContext:
    cell: CellConfig
    sim: SimConfig
    world: World
    clock: SimClock
    log_dir: Path | None = None
    pty: bool = False            # serial devices on ptys instead of loopback TCP
    ephemeral: bool = False      # bind port 0 (tests), report the real URL
    faults: str = ""             # seeded fault spec (sim.yaml's, or --fault)
    config_dir: Path | None = None


@dataclass
class Served:
    device: str                  # robot, cnc, power_source, cellio
    url: str                     # what a driver connects to
    close: Callable[[], Awaitable[None]]
    sim: object = None           # the simulator object (tests reach its state, e.g. open the door)
    extra: dict[str, object] = field(default_factory=dict)

    def describe(self) -> dict[str, object]:
        return {"device": self.device, "url": self.url, **self.extra}


def attach(ctx: SimContext) -> ProcessPhysics | None:
    """Give `ctx.world` its process physics once (every simulator's `serve` calls this)."""
    world = ctx.world
    if world is None or not hasattr(world, "use_physics"):
        return None
    if world.physics is None:
        material = load_material(ctx.cell.cell.material)
        seed = parse_fault_spec(ctx.faults or ctx.sim.faults).seed
        world.use_physics(ProcessPhysics(material, ctx.sim.process, seed=seed))
    return world.physics
