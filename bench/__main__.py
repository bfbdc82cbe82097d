"""`make bench`: run every benchmark module in bench/ (each has a `main()`), print their figures."""
from __future__ import annotations

import importlib
import pkgutil
import sys
from pathlib import Path


def main() -> int:
    names = sorted(m.name for m in pkgutil.iter_modules([str(Path(__file__).parent)]) if not m.name.startswith("_"))
    only = sys.argv[1:]
    failed = 0
    for name in names:
        if only and name not in only:
            continue
        mod = importlib.import_module(f"bench.{name}")
        if not hasattr(mod, "main"):
            continue
        print(f"== bench.{name}", flush=True)
        try:
            rc = mod.main([])
        except SystemExit as exc:  # a benchmark may exit with its status
            rc = exc.code
        failed += bool(rc)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
