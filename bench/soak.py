"""The slow soaks: the tests marked `slow` (excluded from `make test` by pyproject's addopts), with
their printed figures, e.g. the real firmwares' safe stop five times each.

Run: .venv/bin/python -m bench.soak [pytest args, e.g. -k safe_stop]
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    cmd = [sys.executable, "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider", "-m", "slow", "tests", *args]
    print(" ".join(cmd), flush=True)
    return subprocess.call(cmd, cwd=ROOT)


if __name__ == "__main__":
    raise SystemExit(main())
