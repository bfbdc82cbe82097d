"""The per-user runtime directory the cell's processes meet in (locks, the simulators' clock)."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path


def runtime_dir() -> Path:
    """`$CELL_LOCK_DIR` when set (the tests give each worker its own), else `$XDG_RUNTIME_DIR/cell`
    (per user, on tmpfs, cleared at boot), else `<tempdir>/cell-<uid>`."""
    env = os.environ.get("CELL_LOCK_DIR")
    if env:
        return Path(env)
    run = os.environ.get("XDG_RUNTIME_DIR")
    if run and Path(run).is_dir():
        return Path(run) / "cell"
    return Path(tempfile.gettempdir()) / f"cell-{os.getuid()}"
