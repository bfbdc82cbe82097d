"""A recorded view for snapshot tests and screenshots: the TUI's session interface, no cell behind it."""
from __future__ import annotations

import concurrent.futures
from pathlib import Path
from typing import Any

from controller.tui.view import LogRow, View
from core.errors import CellError


class ReplaySession:
    """A recorded, fixed view: for snapshot tests and screenshots (no clock, no devices)."""

    def __init__(self, view: View, log: list[LogRow] | None = None) -> None:
        self._view = view
        self._log = list(log or [])
        self.refused: list[str] = []

    def start(self) -> concurrent.futures.Future[None]:
        f: concurrent.futures.Future[None] = concurrent.futures.Future()
        f.set_result(None)
        return f

    def view(self) -> View:
        return self._view

    def log_rows(self, after_id: int = 0, limit: int = 2000) -> list[LogRow]:
        return [r for r in self._log if r.id > after_id][:limit]

    def ui_log(self) -> list[LogRow]:
        return []

    def _refuse(self, what: str) -> concurrent.futures.Future[Any]:
        self.refused.append(what)
        f: concurrent.futures.Future[Any] = concurrent.futures.Future()
        f.set_exception(CellError(f"'{what}' is not available in a recorded view"))
        return f

    def command(self, name: str) -> concurrent.futures.Future[Any]:
        return self._refuse(name)

    def choose_file(self, path: str | Path, width_mm: float | None = None) -> concurrent.futures.Future[Any]:
        return self._refuse("open")

    def plan(self, width_mm: float | None = None) -> concurrent.futures.Future[Any]:
        return self._refuse("plan")

    def connect(self) -> concurrent.futures.Future[Any]:
        return self._refuse("connect")

    def apply_alignment(self) -> concurrent.futures.Future[Any]:
        return self._refuse("apply_alignment")

    def stop_safely(self) -> concurrent.futures.Future[bool]:
        f: concurrent.futures.Future[bool] = concurrent.futures.Future()
        f.set_result(False)
        return f

    def build_active(self) -> bool:
        st = self._view.snap.state
        return st.startswith("running_") or st == "paused"

    def close(self, timeout: float = 10.0) -> None:
        pass

    def trace_to_ask(self) -> list[str]:
        """A replay starts no build: the start dialog never asks (docs/records.md)."""
        return []
