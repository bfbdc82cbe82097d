"""One simulated cell of bench/records_fleet.py: its simulators in this process, one controller,
its jobs built one after the other through the controller's API (the start point the TUI uses),
each build's record written and sent by the controller as at the end of every build.

    python -m bench._fleet_cell CELL_YAML RUNS_DIR JOB...

Prints one JSON line per build: the job, the state, the run directory. One process per cell, so
its imports and its simulators' start are paid once, not once per job (ten cells started 30
interpreters, and 25 of their simulator sets did not come up within 20 s on the shared host).
"""
from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path

from controller.harness.cell import open_cell
from controller.job.read import read_job
from core.config import load_cell, load_sim


async def build_all(cfg_path: Path, runs: Path, jobs: list[Path]) -> None:
    # ten cells' simulators coming up beside each other on a loaded host: minutes, not 20 s
    async with open_cell(load_cell(cfg_path), sim=load_sim(), log_dir=runs / "sim", runs_dir=runs,
                         start_timeout_s=300.0) as ctl:
        for j in jobs:
            if ctl.machine.can("reset"):   # a fault latched by the previous build: the operator's reset
                await ctl.reset()
            ctl.open_job(read_job(j))
            res = await ctl.start()
            print(json.dumps({"job": str(j), "state": res.state, "run_dir": str(ctl.run_dir),
                              "record": str(ctl.last_report) if ctl.last_report else None,
                              "message": ctl.snapshot().message}), flush=True)


def main(argv: list[str]) -> int:
    asyncio.run(build_all(Path(argv[0]), Path(argv[1]), [Path(a) for a in argv[2:]]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
