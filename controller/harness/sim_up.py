"""`cell sim up`: every simulator served on the URLs of cell.yaml, in this process, until Ctrl-C."""
from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path
from typing import Any

from core.config import CellConfig, SimConfig, load_material
from sims.clock import SimClock
from sims.loop import precise_loop
from sims.up import SimContext, run_forever
from sims.world import World


def serve_until_interrupted(cell: CellConfig, sim: SimConfig, log_dir: Path | None, *, pty: bool = False,
                            faults: str = "") -> None:
    """Serve every device; one JSON line per simulator with its URL on stdout once all are up."""
    mat = load_material(cell.cell.material)
    ctx = SimContext(
        cell=cell, sim=sim, world=World(log_dir, arc_efficiency=mat.arc_efficiency, defer_lays=True),
        clock=SimClock(cell.cell.time_scale), log_dir=log_dir, pty=pty, faults=faults,
    )

    def ready(served: list[Any]) -> None:
        for s in served:
            sys.stdout.write(json.dumps(s.describe()) + "\n")
        sys.stdout.flush()

    try:
        with asyncio.Runner(loop_factory=precise_loop) as runner:   # timers on time (sims/loop.py)
            runner.run(run_forever(ctx, ready))
    except KeyboardInterrupt:
        pass
