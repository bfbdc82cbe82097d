"""Peak memory of `cell plan` on a large mesh (issue 14: < 2 GB for inputs up to 5 million
faces), and of the refusals of the bounded-resource guards.

    python -m bench.input_limits [--faces 5000000]

Writes a binary STL sphere (radius 40 mm) of about --faces triangles, runs `cell plan` on it in
a subprocess and reports its wall time and peak RSS (ru_maxrss of the child).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def sphere_stl(path: Path, faces: int, r: float = 40.0) -> int:
    """A UV sphere of about `faces` triangles written as binary STL (z from 0 to 2r)."""
    n = max(8, int((faces / 2) ** 0.5))
    th = np.linspace(0, np.pi, n + 1)
    ph = np.linspace(0, 2 * np.pi, n + 1)
    T, P = np.meshgrid(th, ph, indexing="ij")
    V = np.stack([r * np.sin(T) * np.cos(P), r * np.sin(T) * np.sin(P), r - r * np.cos(T)], axis=-1)
    a, b, c, d = V[:-1, :-1], V[1:, :-1], V[1:, 1:], V[:-1, 1:]
    tri = np.concatenate([np.stack([a, b, c], axis=2).reshape(-1, 3, 3), np.stack([a, c, d], axis=2).reshape(-1, 3, 3)])
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    tri = tri[area > 1e-12]
    rec = np.zeros(len(tri), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["v"] = tri
    with path.open("wb") as f:
        f.write(b"\0" * 80 + np.uint32(len(tri)).tobytes())
        f.write(rec.tobytes())
    return len(tri)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--faces", type=int, default=5_000_000)
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as d:
        stl = Path(d) / "sphere.stl"
        n = sphere_stl(stl, a.faces)
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, "-m", "controller.cli.main", "plan", str(stl), "--width", "7",
                            "--out", str(Path(d) / "o.json"), "--json", "--allow-underfill", "--allow-overhang"],
                           capture_output=True, text=True, check=False, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
        wall = time.monotonic() - t0
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    print(json.dumps({"faces": n, "exit": r.returncode, "stderr": r.stderr.strip()[-300:], "wall_s": round(wall, 1),
                      "peak_rss_mb": round(peak_mb, 1), "limit_mb": 2048, "ok": peak_mb < 2048}, indent=1))
    return 0 if peak_mb < 2048 and r.returncode in (0, 1, 2) else 1


if __name__ == "__main__":
    raise SystemExit(main())
