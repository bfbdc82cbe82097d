"""Shared test fixtures."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# One controller per cell (controller/runtime/cell_lock.py): each test worker process gets a lock
# directory of its own, so two test files building the demo cell at once on two workers are not
# refused as a second controller (tests/test_stops.py checks the refusal in a directory of its own).
os.environ["CELL_LOCK_DIR"] = tempfile.mkdtemp(prefix=f"cell-locks-{os.environ.get('PYTEST_XDIST_WORKER', 'main')}-")
# Validated configuration remembered by `cell plan` (core/config_cache.py): a directory per test
# worker, never the user's ~/.cache.
os.environ["CELL_CACHE_DIR"] = tempfile.mkdtemp(prefix=f"cell-cache-{os.environ.get('PYTEST_XDIST_WORKER', 'main')}-")
SHARED_PARTS = ROOT.parent / "shared" / "parts"


# A cell on the wall clock (`pytestmark = pytest.mark.realtime`): its bounds are device cycles and
# latencies. Under `make test` the other xdist worker runs a real-time cell of its own on the same
# two cores, and a test whose bound that starved gets one more run (pytest-rerunfailures; the
# summary counts the reruns). Run alone (no worker beside it, e.g. `pytest tests/test_stops.py`)
# every real-time test is strict. docs/testing.md says why.
RERUNS_BESIDE_ANOTHER_WORKER = 1


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) < 2:
        return
    for item in items:
        if item.get_closest_marker("realtime") is not None and item.get_closest_marker("flaky") is None:
            item.add_marker(pytest.mark.flaky(reruns=RERUNS_BESIDE_ANOTHER_WORKER))


@pytest.fixture
def shared_parts() -> Path:
    """The real STL files of ../shared/parts; tests using them skip when absent."""
    if not SHARED_PARTS.is_dir():
        pytest.skip("../shared/parts is not present")
    return SHARED_PARTS
