"""Whose fault a late device cycle is (drivers/loop_times.py; docs/testing.md, "A loop that never blocks")."""
from __future__ import annotations

import threading
import time

import pytest

from drivers.loop_times import Blame, LoopClock, LoopSample, blame, device_thread


def at(t: float = 0.0, loop_cpu: float = 0.0, loop_wait: float = 0.0, proc_cpu: float = 0.0,
       dev_cpu: float = 0.0, other_wait: float = 0.0) -> LoopSample:
    return LoopSample(t, loop_cpu, loop_wait, proc_cpu, dev_cpu, other_wait)


def test_the_loops_own_work_is_the_controllers() -> None:
    # 30 ms late, the loop ran 28 ms of CPU: computing on the device loop
    share = blame(0.030, at(), at(0.040, loop_cpu=0.028, proc_cpu=0.028))
    assert share.own == pytest.approx(0.028) and share.os == pytest.approx(0.002) and share.devices == 0.0


def test_waiting_for_a_cpu_is_the_os_even_when_other_threads_of_ours_ran() -> None:
    # another worker's real-time cell had the CPU for 35 ms; our pool thread ran 30 ms on the other
    # core meanwhile (the old attribution blamed the controller for it)
    share = blame(0.035, at(), at(0.045, loop_cpu=0.001, loop_wait=0.034, proc_cpu=0.031))
    assert share.os == pytest.approx(0.034) and share.own == pytest.approx(0.001)


def test_the_gil_held_by_a_simulator_is_the_devices_and_by_the_screen_the_controllers() -> None:
    # 40 ms asleep past the timer; the simulators ran 30 ms, the TUI's thread 10 ms
    share = blame(0.040, at(), at(0.050, proc_cpu=0.040, dev_cpu=0.030))
    assert share.devices == pytest.approx(0.030) and share.own == pytest.approx(0.010) and share.os == 0.0


def test_a_simulator_that_answers_late_because_it_computed_is_the_devices() -> None:
    # a 40 ms period: its timers fired 5 ms late, and 25 ms it waited for the in-process cell
    # I/O's reply; meanwhile the simulators computed 22 ms and the screen 5 ms
    share = blame(0.005, at(), at(0.040, proc_cpu=0.027, dev_cpu=0.022), waited=0.025)
    assert share.devices == pytest.approx(0.022)                   # all of the simulators' time
    assert share.own == pytest.approx(0.005 * 5 / 27)               # the screen's part of the late timers
    assert share.own + share.os + share.devices <= 0.030 + 1e-9
    # a real device (no simulator thread of ours) that answers late is nobody's share here
    assert blame(0.005, at(), at(0.040, proc_cpu=0.005), waited=0.025).devices == 0.0


def test_a_preempted_holder_of_the_gil_is_the_os() -> None:
    # 40 ms asleep past the timer; our other thread ran 5 ms and waited 35 ms for a CPU
    share = blame(0.040, at(), at(0.050, proc_cpu=0.005, other_wait=0.035))
    assert share.own == pytest.approx(0.005) and share.os == pytest.approx(0.035)
    # nothing of ours ran at all (a virtual CPU taken away): the host's
    assert blame(0.040, at(), at(0.050)) == Blame(0.0, 0.040, 0.0)


def test_the_clock_reads_this_threads_cpu_and_another_threads_wait() -> None:
    clock = LoopClock()
    stop = threading.Event()

    def spin() -> None:
        device_thread(threading.get_ident())
        while not stop.is_set():
            sum(range(1000))
        device_thread(threading.get_ident(), present=False)

    try:
        a = clock.sample()
        t0 = time.thread_time()
        while time.thread_time() - t0 < 0.05:
            sum(range(1000))
        th = threading.Thread(target=spin)
        th.start()
        time.sleep(0.1)
        b = clock.sample()
        stop.set()
        th.join()
    finally:
        clock.close()
    assert b.loop_cpu - a.loop_cpu >= 0.045           # the 50 ms this thread spun
    assert b.dev_cpu - a.dev_cpu > 0.01               # the device thread's CPU, told apart
    assert b.proc_cpu - a.proc_cpu >= (b.loop_cpu - a.loop_cpu) + (b.dev_cpu - a.dev_cpu) - 0.005
