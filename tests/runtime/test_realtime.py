"""The host set-up the device cycles ask for (core/realtime.py), and that it is given back."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from controller import BLAS_THREAD_VARS

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.skipif(not os.access("/dev/cpu_dma_latency", os.W_OK), reason="needs root and /dev/cpu_dma_latency")
def test_the_cpu_latency_request_is_held_while_cycling_and_withdrawn_by_relax():
    # in a child process: the request is process-wide and must not leak into the test worker
    code = """
import os
from core import realtime
def held():
    links = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            links.append(os.readlink(f"/proc/self/fd/{fd}"))
        except OSError:   # the directory listing's own descriptor, gone already
            pass
    return "/dev/cpu_dma_latency" in links
print(held())
print(realtime.keep_cpus_awake().startswith("CPU wake-up latency 0"))
print(held())
realtime.relax()
print(held())
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert out.stdout.split() == ["False", "True", "True", "False"], out.stderr[-2000:]


def _threads_after_numpy(prelude: str) -> int:
    code = prelude + "\nimport numpy, os\nprint(len(os.listdir('/proc/self/task')))\n"
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARS}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    return int(out.stdout.split()[-1])


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="counts threads in /proc")
def test_a_cell_process_runs_numpy_on_one_thread():
    # OpenBLAS's workers are time-shared threads the real-time device loop waited on: 50-60 ms
    # stalls of the simulators beside a CPU hog (docs/false-trips.md). Every `cell` process (its
    # entry point imports the controller package first) keeps numpy to the thread that calls it.
    bare = _threads_after_numpy("")
    cell = _threads_after_numpy("import controller.cli.main")
    assert cell == 1, (bare, cell)
    if (os.cpu_count() or 1) > 1:
        assert bare > 1          # the hazard is real here: numpy alone starts worker threads
