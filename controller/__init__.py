"""Time, state and safety: configuration, the build state machine, alignment, journal, CLI, TUI."""
import os

# One BLAS thread in every process of the cell (`cell run`, `cell sim up`, …), set before numpy
# loads OpenBLAS. The device cycles run at real-time priority; numpy handed a small operation to an
# OpenBLAS worker thread, which is time-shared: beside a CPU-bound neighbour it ran only when the
# scheduler let it, and the real-time loop waiting on it stalled for 50-60 ms (the simulators'
# replies late: "no reply within 50 ms"; docs/false-trips.md). The arrays here are small: a second
# BLAS thread buys nothing. An explicit setting in the environment wins.
BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread() -> None:
    """Ask numpy's BLAS for one thread (effective only before numpy is first imported)."""
    for var in BLAS_THREAD_VARS:
        os.environ.setdefault(var, "1")


one_blas_thread()
