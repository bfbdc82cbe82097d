"""Keeping a process's cyclic I/O on time: real-time priority and a collector that never stalls.

Both the controller and the simulators' process (`cell sim up`) answer or drive 10 ms device
cycles. Two things stalled them under ordinary load (measured with py-spy and gc callbacks,
docs/false-trips.md): full garbage collections of a heap holding numpy, trimesh, pymodbus…
(58–84 ms in the simulators' process) and time-shared scheduling beside CPU-bound processes
on a 2-core machine. `quiet_gc()` and `elevate()` remove them.
"""
from __future__ import annotations

import concurrent.futures
import gc
import os
import struct
import threading

RT_PRIORITY = 20       # SCHED_FIFO priority of the controller's device cycles; below the kernel's threads (50)
SIM_RT_PRIORITY = 30   # the simulators stand for devices with CPUs of their own: they preempt the host
# A thread that shares the interpreter lock with the device cycles (the controller's worker
# threads): below the device cycles and the journal writer, above time-shared
# processes, so that they never preempt it while it holds the lock the device cycles wait for
# (`share_the_lock`).
LOCK_SHARER_RT_PRIORITY = 10


_DEFAULT_THRESHOLDS = gc.get_threshold()
NO_FULL_COLLECTIONS = 1_000_000_000   # gen-2 threshold while device cycles run


def quiet_gc(collect: bool = False) -> None:
    """Keep the collector from stalling the device cycles.

    Everything alive now is frozen (never scanned again) and full (generation 2) collections
    are put off: even over the objects a build allocates after the freeze one took 65 ms in the
    controller, longer than a link's `lost_after_cycles` × 10 ms. Young generations are still
    collected (a few ms). `collect` first frees what is garbage already: only where that pause is
    harmless (before any device traffic). `relax()` restores the default thresholds.
    """
    if collect:
        gc.collect()
    gc.freeze()
    t0, t1, _ = gc.get_threshold()
    gc.set_threshold(t0, t1, NO_FULL_COLLECTIONS)


def elevate(what: str, priority: int = RT_PRIORITY, round_robin: bool = False) -> str:
    """Ask for SCHED_FIFO (`round_robin`: SCHED_RR) for the calling thread only: with
    SCHED_RESET_ON_FORK neither the threads it starts nor its child processes inherit it (an I/O
    thread elevates itself).

    Returns one line for the log: what was obtained, or why not and what to do about it.
    Heavy work never runs under SCHED_FIFO: a FIFO thread is never time-sliced, so a busy one
    would starve every other FIFO thread of its priority on that core. The threads that share the
    interpreter lock with the device cycles (`share_the_lock`) run SCHED_RR below them.
    """
    if not hasattr(os, "sched_setscheduler"):
        return f"{what}: no real-time scheduling on this OS; cycle timing may suffer under load"
    base = os.SCHED_RR if round_robin else os.SCHED_FIFO
    try:
        prio = min(priority, os.sched_get_priority_max(base))
        policy = base | getattr(os, "SCHED_RESET_ON_FORK", 0)
        os.sched_setscheduler(0, policy, os.sched_param(prio))
    except (PermissionError, OSError) as exc:
        return (f"{what}: cannot get real-time priority ({exc.strerror or exc}); run as root or grant "
                "CAP_SYS_NICE (e.g. `setcap cap_sys_nice+ep` on the interpreter) so that CPU load cannot "
                "delay the 10 ms device cycles")
    return f"{what}: {'SCHED_RR' if round_robin else 'SCHED_FIFO'} priority {prio}; {keep_cpus_awake()}"


def share_the_lock(what: str) -> str:
    """The calling thread shares the interpreter lock with the device cycles (the controller's
    worker threads): SCHED_RR at LOCK_SHARER_RT_PRIORITY, below the device cycles and
    the journal writer, time-sliced among its peers. Time-shared, such a thread was preempted by
    other processes while it held the lock, and the real-time device cycles slept on the lock for
    as long (up to 720 ms measured at load 9; docs/controller.md, "Threads that share the
    interpreter lock")."""
    return elevate(what, LOCK_SHARER_RT_PRIORITY, round_robin=True)


_LATENCY_REQUEST = None   # the open /dev/cpu_dma_latency while this process holds its request


def keep_cpus_awake() -> str:
    """Ask the kernel (PM QoS) for a CPU wake-up latency of 0 until `relax()` (or the process ends).

    An idle CPU halts; waking it (on a virtual machine, the host scheduling the virtual CPU again)
    took 40-80 ms now and then on this machine, while a busy one answered within 11 ms: the
    simulators' replies were late only on an otherwise idle machine. Holding a 0 µs request keeps
    the idle CPUs polling instead of halting, the usual set-up of a real-time Linux host
    (cyclictest does the same). Root only; one log line says what was obtained.
    """
    global _LATENCY_REQUEST
    if _LATENCY_REQUEST is not None:
        return "CPU wake-up latency request already held"
    try:
        f = open("/dev/cpu_dma_latency", "wb", buffering=0)  # noqa: SIM115 - held open on purpose
        f.write(struct.pack("i", 0))
    except OSError as exc:
        return (f"cannot hold the CPUs awake ({exc.strerror or exc}); idle CPUs may wake late under a "
                "virtual machine: run as root or set a 0 µs latency in the BIOS / kernel (idle=poll)")
    _LATENCY_REQUEST = f
    return "CPU wake-up latency 0 µs requested (/dev/cpu_dma_latency)"


def is_realtime() -> bool:
    """Whether the calling thread runs under SCHED_FIFO (or SCHED_RR)."""
    try:
        return os.sched_getscheduler(0) & ~getattr(os, "SCHED_RESET_ON_FORK", 0) in (os.SCHED_FIFO, os.SCHED_RR)
    except (AttributeError, OSError):
        return False


UI_NICE = -10   # the TUI's thread: time-shared, at ten times a default process's CPU weight


def favour(what: str, nice: int = UI_NICE) -> str:
    """The calling thread stays time-shared but at `nice` (Linux: per thread): a thread that shares
    the interpreter lock with the device cycles and is busy often (the TUI's screen, 0.2-0.27 CPU-s
    a build second). Real-time, it ran whenever it could and took the lock from the device cycles
    every switch interval (the TUI main flow's longest period 28-35 ms against 22-26 time-shared,
    load 5-7); time-shared at the default weight, other processes preempted it while it held the
    lock (77-105 ms, error 50 at load 9-15). At nice -10 they rarely do (docs/controller.md)."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
    except (AttributeError, PermissionError, OSError) as exc:
        return f"{what}: cannot raise its CPU weight ({getattr(exc, 'strerror', None) or exc})"
    return f"{what}: nice {nice}"


def lock_sharing_executor() -> concurrent.futures.ThreadPoolExecutor:
    """A thread pool whose workers `share_the_lock`: the device loop's default executor, where the
    controller hands its work off the loop (`asyncio.to_thread`: the job's checks, the feed check,
    records). Time-shared, one of them held the lock while preempted and the device cycles waited
    720 ms on it at load 9."""
    return concurrent.futures.ThreadPoolExecutor(thread_name_prefix="controller-worker",
                                                 initializer=share_the_lock, initargs=("controller worker",))


def relax_thread() -> None:
    """The calling thread back to time-shared scheduling at the default weight (after `elevate` or
    `favour`; nothing else changes)."""
    try:
        if is_realtime():
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 0)
    except (AttributeError, OSError):
        pass


def relax() -> None:
    """Back to time-shared scheduling, the default collector and sleeping idle CPUs (after the
    devices are closed)."""
    global _LATENCY_REQUEST
    gc.set_threshold(*_DEFAULT_THRESHOLDS)
    if _LATENCY_REQUEST is not None:   # closing the file withdraws the PM QoS request
        _LATENCY_REQUEST.close()
        _LATENCY_REQUEST = None
    try:
        if is_realtime():
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError):
        pass
