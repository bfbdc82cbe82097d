"""A real PostgreSQL server on a temporary directory and a free port, from the distribution's
packages (Debian's `postgresql`: /usr/lib/postgresql/N/bin), for the tests and the benches of the
record store (docs/records.md). No mock: initdb, pg_ctl, a server on 127.0.0.1.

initdb refuses to run as root: as root (CI), the server runs as the `postgres` user the package
creates (`runuser -u postgres`), on a directory given to that user. `.ci/run` installs the
packages when the binaries are absent.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path
from typing import Iterator


def server_bin() -> Path | None:
    """The newest installed PostgreSQL server's bin directory (None: not installed)."""
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/initdb"),
                   key=lambda p: int(p.parent.parent.name) if p.parent.parent.name.isdigit() else 0)
    if found:
        return found[-1].parent
    w = shutil.which("initdb")
    return Path(w).parent if w else None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


class PgServer:
    """initdb on a temporary directory, pg_ctl start/stop on a free port; `url(db)` to reach it."""

    def __init__(self, bindir: Path, *, user: str = "cell") -> None:
        self.bindir = bindir
        self.user = user
        self.base = Path(tempfile.mkdtemp(prefix="cell-pg-"))
        self.data = self.base / "data"
        self.port = free_port()
        self.log = self.base / "server.log"
        self._as = ["runuser", "-u", "postgres", "--"] if os.geteuid() == 0 else []
        if self._as:
            shutil.chown(self.base, "postgres", "postgres")
        self._run("initdb", "-D", str(self.data), "-A", "trust", "-U", user, "-E", "UTF8", "--no-sync", "--no-locale")

    def _run(self, tool: str, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        cmd = [*self._as, str(self.bindir / tool), *args]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
        if check and proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)}: exit {proc.returncode}: {proc.stderr.strip()[-800:]}")
        return proc

    def start(self) -> None:
        opts = (f"-p {self.port} -k {self.base} -c listen_addresses=127.0.0.1 -c fsync=off "
                "-c synchronous_commit=off -c full_page_writes=off -c max_connections=200")
        self._run("pg_ctl", "-D", str(self.data), "-o", opts, "-l", str(self.log), "-w", "-t", "60", "start")

    def stop(self, mode: str = "fast") -> None:
        self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "-t", "60", "stop", check=False)

    def url(self, db: str = "postgres") -> str:
        return f"postgresql://{self.user}@127.0.0.1:{self.port}/{db}"

    def create_db(self, name: str) -> str:
        """A fresh database on the server; its URL."""
        # lazy: psycopg only where a server runs
        import psycopg

        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}"')
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def close(self) -> None:
        self.stop("immediate")
        shutil.rmtree(self.base, ignore_errors=True)


@contextlib.contextmanager
def running() -> Iterator[PgServer]:
    """A started server, stopped and removed on exit; RuntimeError when the binaries are absent."""
    bindir = server_bin()
    if bindir is None:
        raise RuntimeError("PostgreSQL server binaries not found (apt-get install postgresql; .ci/run does)")
    srv = PgServer(bindir)
    try:
        srv.start()
        yield srv
    finally:
        srv.close()
