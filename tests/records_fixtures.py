"""The record store's fixtures (docs/records.md): a real PostgreSQL server started by the test
session from the distribution's packages (bench/_postgres.py), and the same tests against SQLite."""
from __future__ import annotations

import itertools
from pathlib import Path
from typing import Iterator

import pytest

from bench._postgres import PgServer, server_bin

_names = itertools.count()


@pytest.fixture(scope="session")
def pg_server() -> Iterator[PgServer]:
    """One PostgreSQL server per test process (a worker of `make test`), on a free port."""
    bindir = server_bin()
    if bindir is None:   # .ci/run installs them: a skip here means a machine set up by hand
        pytest.skip("PostgreSQL server binaries absent (apt-get install postgresql; .ci/run installs them)")
    srv = PgServer(bindir)
    srv.start()
    try:
        yield srv
    finally:
        srv.close()


@pytest.fixture(params=["sqlite", "postgresql"])
def store_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A fresh, empty store: a SQLite file, or a new database on the session's PostgreSQL server."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'shop.sqlite'}"
    srv: PgServer = request.getfixturevalue("pg_server")
    return srv.create_db(f"t{next(_names)}")
