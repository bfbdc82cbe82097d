"""One connection to the record store, whichever database it is (docs/records.md).

`sqlite:///PATH` opens the file with the standard library; `postgresql://...` with psycopg 3,
imported only then (`cell plan` and every cell without a store never load it). The SQL of the
store is written once, with `?` placeholders; for PostgreSQL they become `%s`. Both run in
explicit transactions (`transaction()`), so a record is stored whole or not at all.
"""
from __future__ import annotations

import contextlib
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Protocol, Sequence

from controller.records.schema import migrate
from core.errors import CellError

Params = Sequence[Any]


class StoreUnreachable(CellError):
    """The record store cannot be reached or refused the write: the record stays queued."""


class _Cursor(Protocol):
    rowcount: int

    def fetchall(self) -> list[Any]: ...


def redact(url: str) -> str:
    """The URL without its password (for messages and the queue files)."""
    head, sep, tail = url.partition("://")
    if not sep or "@" not in tail:
        return url
    cred, _, host = tail.rpartition("@")
    user = cred.split(":", 1)[0]
    return f"{head}://{user}:***@{host}" if ":" in cred else url


@dataclass
class Store:
    """A connection to the store; `dialect` is "sqlite" or "postgresql"."""

    dialect: str
    conn: Any      # sqlite3.Connection or psycopg.Connection: the same execute/close, told apart by dialect
    url: str

    def _sql(self, sql: str) -> str:
        return sql.replace("?", "%s") if self.dialect == "postgresql" else sql

    def execute(self, sql: str, params: Params = ()) -> _Cursor:
        cur: _Cursor = self.conn.execute(self._sql(sql), tuple(params))
        return cur

    def rows(self, sql: str, params: Params = ()) -> list[tuple[Any, ...]]:
        return [tuple(r) for r in self.execute(sql, params).fetchall()]

    def executemany(self, sql: str, seq: Sequence[Params]) -> None:
        if not seq:
            return
        if self.dialect == "postgresql":
            with self.conn.cursor() as cur:   # psycopg pipelines executemany
                cur.executemany(self._sql(sql), [tuple(p) for p in seq])
        else:
            self.conn.executemany(sql, [tuple(p) for p in seq])

    @contextlib.contextmanager
    def transaction(self, *, lock: str | None = None) -> Iterator[None]:
        """BEGIN … COMMIT (ROLLBACK on an error). `lock`: a name serialising the writers that give it
        (PostgreSQL: a transaction-scoped advisory lock; SQLite: BEGIN IMMEDIATE serialises them all)."""
        if self.dialect == "postgresql":
            self.conn.execute("BEGIN")
            if lock is not None:
                self.conn.execute("SELECT pg_advisory_xact_lock(hashtext(%s))", (lock,))
        else:
            self.conn.execute("BEGIN IMMEDIATE")
        try:
            yield
        except BaseException:
            self.conn.execute("ROLLBACK")
            raise
        self.conn.execute("COMMIT")

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.conn.close()


def sqlite_path(url: str) -> Path:
    return Path(url[len("sqlite:///"):])


def connect(url: str, timeout_s: float = 5.0) -> Store:
    """Open the store at `url` and bring its schema up to date (controller/records/schema.py);
    StoreUnreachable naming the URL (without its password) when it cannot be reached."""
    store = _open(url, timeout_s)
    try:
        migrate(store)
    except Exception as exc:
        store.close()
        raise _unreachable(url, exc) from None
    return store


def _open(url: str, timeout_s: float) -> Store:
    if url.startswith("sqlite:///"):
        path = sqlite_path(url)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            conn = sqlite3.connect(str(path), timeout=max(timeout_s, 30.0), isolation_level=None)
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA foreign_keys=ON")
        except (OSError, sqlite3.Error) as exc:
            raise _unreachable(url, exc) from None
        return Store("sqlite", conn, url)
    if url.startswith(("postgresql://", "postgres://")):
        # lazy: psycopg loads only for a PostgreSQL store (start-up time of every other command)
        import psycopg

        t0 = time.monotonic()
        try:
            pg = psycopg.connect(url, autocommit=True, connect_timeout=max(1, round(timeout_s)))
        except psycopg.Error as exc:
            raise _unreachable(url, exc, time.monotonic() - t0) from None
        return Store("postgresql", pg, url)
    raise CellError(f"records url {redact(url)!r}: expected sqlite:///PATH or postgresql://USER@HOST:PORT/DB")


def _unreachable(url: str, exc: BaseException, waited: float | None = None) -> StoreUnreachable:
    text = " ".join(str(exc).split())[:300] or type(exc).__name__
    after = f" after {waited:.1f} s" if waited is not None else ""
    return StoreUnreachable(f"record store {redact(url)}: {text}{after}")
