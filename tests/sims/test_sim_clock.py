"""The simulators' process clock: scaled time, and a scale changed while it runs (a repair probes
at the cell's time scale and builds at what the CNC link can feed)."""
from __future__ import annotations

import threading
import time

from sims.clock import SimClock


def test_a_new_scale_goes_on_from_the_same_process_time_without_a_jump() -> None:
    c = SimClock(60.0)
    time.sleep(0.05)
    before = c.now()
    c.set_scale(5.0)
    after = c.now()
    assert 0 <= after - before < 0.01 * 60            # no jump back or forward at the switch
    assert c.time_scale == 5.0 and c.wall(5.0) == 1.0
    time.sleep(0.1)
    assert abs((c.now() - after) - 0.5) < 0.1          # 0.1 s of wall time at 5x


def test_a_reader_on_another_thread_never_sees_time_go_back_across_switches() -> None:
    c = SimClock(60.0)
    back: list[float] = []
    stop = threading.Event()

    def read() -> None:
        last = c.now()
        while not stop.is_set():
            t = c.now()
            if t < last:
                back.append(last - t)
            last = t

    th = threading.Thread(target=read)
    th.start()
    for k in range(400):
        c.set_scale(5.0 if k % 2 else 60.0)
    stop.set()
    th.join()
    assert back == []
