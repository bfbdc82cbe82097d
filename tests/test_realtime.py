"""The host set-up the device cycles ask for (core/realtime.py), and that it is given back."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


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
