"""Start-up plus plan of a 12-face wall with `cell plan` (issue 40 item 3; target <= 0.35 s).

Each run is a fresh interpreter: `python -m controller.cli.main plan wall.stl --width 6` (an 80 x 5.2 x 20
mm wall, one bead a layer), the configuration remembered (the second and later runs, as a user's).
Reports the median wall and CPU time (user + system of the child) and the load average before and
after, since on a shared machine the wall time is the CPU time plus the waiting for a core; and
which of the controller's runtime libraries the plan loaded (none should be).

The project's modules are byte-compiled first, as an install does (pip compiles them; this checkout
runs with PYTHONDONTWRITEBYTECODE=1, so without it every run would compile some 45 modules: 0.07-0.14 s).

Run: .venv/bin/python -m bench.plan_startup [--runs N]
"""
from __future__ import annotations

import argparse
import compileall
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RUNTIME = ("textual", "asyncua", "pymodbus", "serial", "matplotlib", "psycopg", "sqlite3", "scipy", "trimesh",
           "pydantic", "yaml", "drivers", "sims", "controller.runtime", "controller.tui", "controller.report",
           "controller.opcua", "controller.journal", "controller.motion")
PROBE = ("import json, sys\nfrom controller.cli.main import main\nrc = main(sys.argv[1:])\n"
         f"sys.stderr.write(json.dumps(sorted(m for m in {RUNTIME!r} if m in sys.modules)))\n")


def _wall_stl(path: Path) -> None:
    # lazy: only this benchmark's set-up needs them (the timed runs are other processes)
    from shapely.geometry import box  # lazy: set-up only
    from planner.extrude import extrude  # lazy: set-up only

    path.write_bytes(extrude(box(0, 0, 80, 5.2), 20.0).export(file_type="stl"))


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="bench.plan_startup")
    ap.add_argument("--runs", type=int, default=15)
    args = ap.parse_args(argv)
    for pkg in ("core", "planner", "controller"):  # as installed: no module compiled during a timed run
        compileall.compile_dir(str(ROOT / pkg), quiet=1)
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as tmp:
        stl = Path(tmp) / "wall.stl"
        _wall_stl(stl)
        cmd = [sys.executable, "-m", "controller.cli.main", "plan", str(stl), "--width", "6", "--out",
               str(Path(tmp) / "wall.job.json")]
        env = {**os.environ, "CELL_CACHE_DIR": str(Path(tmp) / "cache")}
        subprocess.run(cmd, cwd=ROOT, env=env, check=True, capture_output=True)  # remembers the configuration
        probe = subprocess.run([sys.executable, "-c", PROBE, *cmd[3:]], cwd=ROOT, env=env, capture_output=True,
                               text=True, check=True)
        loaded = probe.stderr.strip().splitlines()[-1]
        load0 = os.getloadavg()[0]
        walls, cpus = [], []
        for _ in range(args.runs):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            subprocess.run(cmd, cwd=ROOT, env=env, check=True, capture_output=True)
            walls.append(time.perf_counter() - t0)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpus.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
        load1 = os.getloadavg()[0]
    wall, cpu = statistics.median(walls), statistics.median(cpus)
    print(f"cell plan of a 12-face wall, {args.runs} runs: wall median {wall:.3f} s (min {min(walls):.3f}, max "
          f"{max(walls):.3f}), cpu median {cpu:.3f} s; load average {load0:.1f} -> {load1:.1f} on "
          f"{os.cpu_count()} cores")
    print(f"runtime libraries the plan loaded: {loaded}")
    ok = wall <= 0.35 and loaded == "[]"
    print(f"target start + plan <= 0.35 s: {'met' if ok else 'MISSED'}"
          + ("" if wall <= 0.35 else f" (cpu {cpu:.3f} s: the rest is waiting for a core)"))
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
