"""One controller per cell (docs/contract.md §6): an exclusive `flock` named after the cell.

Every command that moves a device (`cell run`, `cell resume`, `cell align run`, `cell repair
run`, `cell demo`, a TUI build) takes it before it opens any device and holds it for the life
of the command. The lock file is

    <lock dir>/<cell name>-<8 hex digits of the sha-256 of cell.yaml's absolute path>.lock

- the lock dir is `$CELL_LOCK_DIR` when set, else `$XDG_RUNTIME_DIR/cell` (per user, on tmpfs,
  cleared at boot), else `<tempdir>/cell-<uid>`; it is shared by every runs directory, so
  `--runs elsewhere` does not get around it;
- named after `cell.name` *and* the config file: one cell.yaml is one cell; two different
  cell.yaml files (two worktrees, a test's copy) are two cells even with the same name.

The holder writes its PID, command line and start time into the file; the refused command reads
them for its one line `error: cell '<name>' is in use by PID n (<command>) since <time>`, exit 2.
`flock` belongs to the open file: when the holder dies (even `kill -9`) the kernel releases it
and the next command takes it over; the stale text is overwritten.
"""
from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from core.errors import CellError
from core.runtime_dir import runtime_dir

DEFAULT_CONFIG = Path(__file__).resolve().parent.parent.parent / "config" / "cell.yaml"


class CellInUse(CellError):
    """Another controller holds the cell's lock (exit 2, before any device is opened)."""

    def __init__(self, message: str, pid: int | None) -> None:
        self.pid = pid
        super().__init__(message)


def lock_dir() -> Path:
    return runtime_dir()


def lock_path(cell_name: str, config_path: str | Path | None) -> Path:
    cfg = Path(config_path) if config_path else DEFAULT_CONFIG
    digest = hashlib.sha256(str(cfg.resolve()).encode()).hexdigest()[:8]
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in cell_name) or "cell"
    return lock_dir() / f"{safe}-{digest}.lock"


class CellLock:
    """The held lock of one cell; `release()` (or process exit) frees it. Re-entrant within a
    process (`cell` takes it first thing in main(), the command's guard again): counted."""

    def __init__(self, path: Path, fd: int, cell_name: str) -> None:
        self.path, self.fd, self.cell_name = path, fd, cell_name
        self.count = 1

    def release(self) -> None:
        self.count -= 1
        if self.count > 0 or self.fd < 0:
            return
        _held.pop(self.path, None)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_UN)
        finally:
            os.close(self.fd)
            self.fd = -1

    def __enter__(self) -> "CellLock":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def acquire(cell_name: str, config_path: str | Path | None, command: str | None = None) -> CellLock:
    """Take the cell's lock or raise CellInUse naming the holder (never blocks)."""
    path = lock_path(cell_name, config_path)
    mine = _held.get(path)
    if mine is not None and mine.fd >= 0:
        mine.count += 1
        return mine
    try:
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
    except OSError as exc:
        raise CellError(f"cell lock {path}: cannot create it ({exc.strerror or exc}); "
                        "set CELL_LOCK_DIR to a writable directory") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = _holder(fd)
        os.close(fd)
        raise CellInUse(_in_use(cell_name, holder), holder.get("pid")) from None
    cmd = command or " ".join(["cell", *sys.argv[1:]])
    text = json.dumps({"pid": os.getpid(), "command": cmd, "since": time.time(), "cell": cell_name,
                       "config": str(Path(config_path or DEFAULT_CONFIG).resolve())})
    os.ftruncate(fd, 0)
    os.pwrite(fd, (text + "\n").encode(), 0)
    lock = _held[path] = CellLock(path, fd, cell_name)
    return lock


_held: dict[Path, CellLock] = {}   # the locks this process holds


def early(argv: list[str]) -> CellLock | contextlib.nullcontext[None]:
    """`cell run|resume|demo|tui|align run|repair run`: take the cell's lock first thing (held in a
    `with` for the command's life; nothing to hold for other commands), before
    the heavy imports (pydantic, numpy), so a second controller is refused within a second. The
    cell name is read with plain YAML; anything unreadable is left to the command (which takes the
    lock again, re-entrantly, once its config is validated)."""
    words = [a for a in argv if not a.startswith("-")]
    cmd = words[:2] if words[:1] in (["align"], ["repair"]) else words[:1]
    if cmd not in (["run"], ["resume"], ["demo"], ["tui"], ["align", "run"], ["repair", "run"]):
        return contextlib.nullcontext()
    config = None
    for i, a in enumerate(argv):
        if a in ("--cell-config", "--config" if cmd == ["tui"] else "--cell-config") and i + 1 < len(argv):
            config = argv[i + 1]
        elif a.startswith(("--cell-config=", "--config=" if cmd == ["tui"] else "--cell-config=")):
            config = a.split("=", 1)[1]
    try:
        import yaml  # light; the validated config (pydantic) is loaded by the command itself

        data = yaml.safe_load(Path(config or DEFAULT_CONFIG).read_text(encoding="utf-8"))
        name = str(data["cell"].get("name", "cell")) if isinstance(data.get("cell"), dict) else "cell"
    except Exception:
        return contextlib.nullcontext()
    return acquire(name, config)


def _holder(fd: int, wait_s: float = 0.3) -> dict[str, Any]:
    """What the holder wrote (it may be between taking the lock and writing: a short retry)."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            raw = os.pread(fd, 4096, 0).decode("utf-8", "replace").strip()
            data = json.loads(raw) if raw else None
        except (OSError, ValueError):
            data = None
        if isinstance(data, dict) or time.monotonic() > deadline:
            return data if isinstance(data, dict) else {}
        time.sleep(0.02)


def _in_use(cell_name: str, holder: dict[str, Any]) -> str:
    pid = holder.get("pid", "?")
    cmd = holder.get("command", "unknown command")
    since = holder.get("since")
    when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(since)) if isinstance(since, (int, float)) else "?"
    return (f"cell '{cell_name}' is in use by PID {pid} ({cmd}) since {when}; "
            "one controller per cell: wait for it to end or stop it")
