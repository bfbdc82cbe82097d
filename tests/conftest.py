"""Shared test fixtures."""
from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED_PARTS = ROOT.parent / "shared" / "parts"


@pytest.fixture
def shared_parts() -> Path:
    """The real STL files of ../shared/parts; tests using them skip when absent."""
    if not SHARED_PARTS.is_dir():
        pytest.skip("../shared/parts is not present")
    return SHARED_PARTS
