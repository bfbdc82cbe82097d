"""A part planned off the controller's loop (the TUI's Job screen): the planner in a child process
of its own, its progress reported line by line, the typed job read back.

Planning is CPU-bound: in a thread of the controller's process it would hold the interpreter lock
long enough to starve the power source's 10 ms cycle and the cell I/O poll (a link timeout, a
fault). The child prints `progress i n` lines, writes the job file, or prints `error <message>`.
"""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable

from controller.job.model import CellJob
from controller.job.read import read_job
from core.config import load_material
from core.errors import CellError

__all__ = ["plan_in_child"]


def plan_in_child(path: str | Path, width_mm: float, material: str,
                  on_progress: Callable[[int, int], None] | None = None) -> CellJob:
    """The part at `path` planned with `width_mm` beads of `material` (a name or a YAML file) in a
    child process; `on_progress(done, total)` as the planner goes. Its error is a CellError naming it."""
    with tempfile.TemporaryDirectory(prefix="cell-plan-") as tmp:
        out = Path(tmp) / "job.json"
        proc = subprocess.Popen([sys.executable, "-m", "controller.api.planning", "plan", str(path), str(width_mm),
                                 material, str(out)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        error = None
        assert proc.stdout is not None
        for line in proc.stdout:
            word, _, rest = line.strip().partition(" ")
            if word == "progress" and on_progress is not None:
                i, n = rest.split()
                on_progress(int(i), int(n))
            elif word == "error":
                error = rest
        err_text = proc.stderr.read() if proc.stderr else ""
        proc.wait()
        if error is not None:
            raise CellError(error)
        if proc.returncode != 0 or not out.exists():
            last = err_text.strip().splitlines()[-1:] or ["no output"]
            raise CellError(f"planning {path}: the planner stopped ({last[0]})")
        return read_job(out)


def plan_main(argv: list[str]) -> int:
    """The child of `plan_in_child`: PATH WIDTH MATERIAL OUT."""
    path, width, material, out = argv
    try:
        # lazy: the planner (shapely, trimesh) loads only in the child that plans
        from planner.job import job_to_dict
        from planner.plan import PlanOptions, plan_part

        def progress(i: int, n: int) -> None:
            print(f"progress {i} {n}", flush=True)

        job = plan_part(path, PlanOptions(width_mm=float(width)), load_material(material), progress=progress)
        Path(out).write_text(json.dumps(job_to_dict(job)), encoding="utf-8")
        print("done", flush=True)
        return 0
    except Exception as exc:  # the message goes to the operator
        print("error " + (str(exc) or exc.__class__.__name__).replace("\n", " "), flush=True)
        return 2


if __name__ == "__main__":
    raise SystemExit(plan_main(sys.argv[2:]))
