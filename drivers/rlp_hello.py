"""The protocol version a robot link speaks, negotiated at connect (docs/protocols/rlp.md §9).

The host asks `!PROTO n` (n the highest version it speaks). A robot that speaks RLP/2 answers
`PROTO m` (m ≤ n, the version in force on this connection from then on); a robot that speaks only
RLP/1 rejects the unknown control frame as any other (`NAK x SYNTAX`). Noise can turn the question
into a SYNTAX error too, so the host settles on RLP/1 only after REFUSALS such answers (or no
answer within its attempts): a wrong fallback costs throughput, never a move. A host that speaks
only RLP/1 never asks, and the robot speaks RLP/1 to it.
"""
from __future__ import annotations

from typing import Awaitable, Callable

from drivers.errors import DeviceTimeout
from wire import rlp

__all__ = ["Hello", "negotiate"]


class Hello:
    """One negotiation's state; the link's reader feeds it the robot's PROTO and NAK frames."""

    REFUSALS = 3       # NAK SYNTAX answers that mean "RLP/1 only"
    ATTEMPTS = 6       # questions at most (CRC NAKs and silence ask again)

    def __init__(self) -> None:
        self.asking = False
        self.answer: int | None = None
        self.refusals = 0

    def on_proto(self, version: int) -> None:
        if self.asking:
            self.answer = version

    def on_nak(self, reason: str) -> None:
        if self.asking and reason == "SYNTAX":
            self.refusals += 1


async def negotiate(hello: Hello, want: int, send: Callable[[bytes], None],
                    wait: Callable[[Callable[[], bool], float], Awaitable[None]], timeout_s: float) -> int:
    """Ask for version `want`; the version both ends speak from now on (1 when `want` is 1)."""
    if want < 2:
        return 1
    hello.asking, hello.answer, hello.refusals = True, None, 0
    try:
        for _ in range(Hello.ATTEMPTS):
            seen = hello.refusals

            def answered(seen: int = seen) -> bool:
                return hello.answer is not None or hello.refusals > seen

            send(rlp.encode(f"!PROTO {want}"))
            try:
                await wait(answered, timeout_s)
            except DeviceTimeout:
                continue
            if hello.answer is not None:
                return hello.answer if hello.answer in rlp.PROTOCOLS and hello.answer <= want else 1
            if hello.refusals >= Hello.REFUSALS:
                return 1
        return 1
    finally:
        hello.asking = False
