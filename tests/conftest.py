"""Shared test fixtures."""
from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from pathlib import Path
from typing import Iterator

import pytest

from controller import one_blas_thread
from tests.link_check import JournalWatch
from tests.records_fixtures import pg_server, store_url  # noqa: F401  (the record store's fixtures: docs/records.md)

ROOT = Path(__file__).resolve().parent.parent
# One BLAS thread in the tests' in-process cells too, as in every `cell` process (controller/__init__.py
# says why): the import above already asked for it, before any test module imports numpy.
one_blas_thread()

# One controller per cell (controller/runtime/cell_lock.py): each test worker process gets a lock
# directory of its own, so two test files building the demo cell at once on two workers are not
# refused as a second controller (tests/runtime/test_stops.py checks the refusal in a directory of its own).
os.environ["CELL_LOCK_DIR"] = tempfile.mkdtemp(prefix=f"cell-locks-{os.environ.get('PYTEST_XDIST_WORKER', 'main')}-")
# Validated configuration remembered by `cell plan` (core/config_cache.py): a directory per test
# worker, never the user's ~/.cache.
os.environ["CELL_CACHE_DIR"] = tempfile.mkdtemp(prefix=f"cell-cache-{os.environ.get('PYTEST_XDIST_WORKER', 'main')}-")
# The build-end record without its PNGs (controller/report/worker.py, docs/build-record.md): drawing
# them is about 1.5 s of every build's 2 s record, and most tests look at what was built, not at
# pictures of it. The tests that check the plots ask for them (the `record_plots` fixture).
os.environ["CELL_RECORD_PLOTS"] = "0"
SHARED_PARTS = ROOT.parent / "shared" / "parts"


# A cell on the wall clock (`pytestmark = pytest.mark.realtime`): its bounds are device cycles and
# latencies. Under `make test` the other xdist workers run real-time cells of their own on the same
# two cores, and a test whose bound that starved gets one more run (pytest-rerunfailures; the
# summary counts the reruns). Run alone (no worker beside it, e.g. `pytest tests/runtime/test_stops.py`)
# every real-time test is strict. docs/testing.md says why.
RERUNS_BESIDE_ANOTHER_WORKER = 1


def pytest_configure(config: pytest.Config) -> None:
    # one lock directory for the session, inherited by the xdist workers (started after this)
    os.environ.setdefault("CELL_TEST_LOCKS", tempfile.mkdtemp(prefix="cell-test-locks-"))


@contextlib.contextmanager
def _cpus(exclusive: bool) -> Iterator[None]:
    """A readers-writer lock across the test workers: tests share the CPUs, a test marked `owns_cpus`
    (or a rerun) waits until the other workers' tests end and holds them alone. The turnstile keeps a
    stream of shared holders from starving the exclusive one."""
    d = Path(os.environ["CELL_TEST_LOCKS"])
    with open(d / "turnstile", "a") as gate, open(d / "cpus", "a") as cpus:
        fcntl.flock(gate, fcntl.LOCK_EX)
        try:
            fcntl.flock(cpus, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        finally:
            if not exclusive:
                fcntl.flock(gate, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(cpus, fcntl.LOCK_UN)
            fcntl.flock(gate, fcntl.LOCK_UN)


@pytest.fixture(autouse=True)
def _share_the_cpus(request: pytest.FixtureRequest) -> Iterator[None]:
    """Tests share the CPUs with each other; an `owns_cpus` test, or a real-time test's rerun, has them
    alone: the other workers wait (the demo's figures: no bead flagged, speed within 5 %; docs/testing.md)."""
    # a rerun (pytest-rerunfailures counts executions): the first run may have been starved by the
    # other workers' tests (a cell, or a planner test: a CPU hog on two cores)
    alone = request.node.get_closest_marker("owns_cpus") is not None or getattr(request.node, "execution_count", 1) > 1
    with _cpus(exclusive=alone):
        yield


_JOURNALS = JournalWatch()


@pytest.fixture(autouse=True)
def _no_late_device_cycle(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Every build of the suite: no power source or cell I/O cycle late by the controller's doing
    (tests/link_check.py; docs/testing.md, "A loop that never blocks"), alone or beside other workers."""
    yield
    late = _JOURNALS.new_late(tmp_path_factory.getbasetemp())
    if late:
        pytest.fail("a device cycle came late because the controller was busy: " + "; ".join(late), pytrace=False)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) < 2:
        return
    for item in items:
        if item.get_closest_marker("realtime") is not None and item.get_closest_marker("flaky") is None:
            item.add_marker(pytest.mark.flaky(reruns=RERUNS_BESIDE_ANOTHER_WORKER))


@pytest.fixture
def record_plots(monkeypatch: pytest.MonkeyPatch) -> None:
    """Build-end records draw their plots, as they do by default outside the tests."""
    monkeypatch.setenv("CELL_RECORD_PLOTS", "1")


@pytest.fixture
def shared_parts() -> Path:
    """The real STL files of ../shared/parts; tests using them skip when absent."""
    if not SHARED_PARTS.is_dir():
        pytest.skip("../shared/parts is not present")
    return SHARED_PARTS
