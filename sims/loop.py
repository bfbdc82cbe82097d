"""The simulators' event loop: timers that fire on time without spinning.

asyncio's default loop on Linux waits in epoll, whose timeout is whole milliseconds rounded up:
every timer fires up to 1 ms late. A robot's EXE sent 1 ms late is, at time scale 120, 0.12 s of
process time, which the host reads as a travel-speed error; waking early and yielding until the
move's end fixed that but spun the CPU at real-time priority (starving the controller beside it
on a busy 2-core machine). select() takes its timeout in microseconds: with the few descriptors
a simulator holds, its cost is the same and its timers are on time.
"""
from __future__ import annotations

import asyncio
import selectors


def precise_loop() -> asyncio.AbstractEventLoop:
    """A new event loop whose timers fire within microseconds of their time (select(), not epoll)."""
    return asyncio.SelectorEventLoop(selectors.SelectSelector())
