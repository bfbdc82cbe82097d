"""A small asyncio adapter over a pyserial `serial_for_url` port (real port, pty, socket://, loop://).

A reader thread feeds received chunks into an asyncio queue; writes are paced at the line rate
(baud/10 bytes/s for 8N1) as a UART would send them, so a driver never piles seconds of frames
into an OS or socket buffer that it can no longer take back (a NAK or a hold then acts at once).
Errors and a closed peer surface as LinkLost naming the device and URL. Shared by the drivers.
"""
from __future__ import annotations

import asyncio
import select
import socket
import threading
import time
from dataclasses import dataclass

import serial

from core.realtime import elevate, is_realtime
from drivers.errors import LinkLost



@dataclass(frozen=True)
class _Closed:
    """The reader thread's last item: the port closed or failed, and why."""

    reason: str


def _tcp_socket(ser: serial.Serial) -> socket.socket | None:
    """The TCP socket under a socket:// port (pyserial keeps it private), else None."""
    sock = getattr(ser, "_socket", None)
    return sock if isinstance(sock, socket.socket) else None


class SerialPort:
    """`await open()`, `await read()` (one chunk), `await write(data)`, `close()`."""

    def __init__(self, url: str, *, baud: int = 115200, name: str = "device", pace: bool = True,
                 pace_factor: float = 0.98) -> None:
        self.url = url
        self.baud = baud
        self.name = name
        self.rate = baud / 10.0 * pace_factor if pace else None
        self.bytes_written = 0
        self.bytes_read = 0
        self.rx_t = 0.0                  # monotonic arrival time of the chunk read() returned last
        self._ser: serial.Serial | None = None
        self._queue: asyncio.Queue[tuple[float, bytes] | _Closed] = asyncio.Queue()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._free_at = 0.0
        self._error: str | None = None
        self._rt = False

    @property
    def is_open(self) -> bool:
        return self._ser is not None and self._error is None

    def _lost(self, what: str) -> LinkLost:
        return LinkLost(f"{self.name} at {self.url}: {what}", reason=what)

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            self._ser = ser = await loop.run_in_executor(
                None, lambda: serial.serial_for_url(self.url, baudrate=self.baud, timeout=0.05, write_timeout=2.0))
        except (serial.SerialException, OSError, ValueError) as exc:
            raise self._lost(f"cannot open the port ({exc}); check the URL and that the device is up") from None
        sock = _tcp_socket(ser)
        if sock is not None:  # socket://: no Nagle delay, frames go out as a UART would send them
            try:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError:
                pass
        self._stop.clear()
        # the reader runs at the loop's priority: a time-shared reader was starved for seconds
        # beside CPU-bound work (the robot's replies unread, the link lost while idle)
        self._rt = is_realtime()
        self._thread = threading.Thread(target=self._reader, args=(ser, loop), name=f"{self.name}-rx", daemon=True)
        self._thread.start()

    def _reader(self, ser: serial.Serial, loop: asyncio.AbstractEventLoop) -> None:
        # pyserial's socket:// reports in_waiting as 0/1 and reads byte by byte: read what is
        # there straight from the socket, so the loop gets chunks, not thousands of 1-byte items
        sock = _tcp_socket(ser)
        if self._rt:
            elevate(f"{self.name} reader")
        try:
            while not self._stop.is_set():
                data = ser.read(1)
                if not data:
                    continue
                if sock is not None:
                    eof = False
                    while len(data) < 65536 and select.select([sock], [], [], 0)[0]:
                        more = sock.recv(65536)
                        if not more:
                            eof = True
                            break
                        data += more
                    loop.call_soon_threadsafe(self._queue.put_nowait, (time.monotonic(), data))
                    if eof:
                        raise serial.SerialException("socket disconnected")
                    continue
                n = ser.in_waiting
                if n:
                    data += ser.read(n)
                loop.call_soon_threadsafe(self._queue.put_nowait, (time.monotonic(), data))
        except Exception as exc:  # closed port or peer: report it once, to the reader
            if not self._stop.is_set():
                try:
                    loop.call_soon_threadsafe(self._queue.put_nowait, _Closed(str(exc)))
                except RuntimeError:
                    pass

    async def read(self) -> bytes:
        """The next received chunk; LinkLost when the port closed or failed."""
        item = await self._queue.get()
        if isinstance(item, _Closed):
            self._error = item.reason
            raise self._lost(item.reason)
        # when the bytes came off the wire (the reader thread's clock): a busy event loop does
        # not delay the time stamps of what the device reported
        self.rx_t, data = item
        self.bytes_read += len(data)
        return data

    async def write(self, data: bytes) -> None:
        """Send `data`, waiting until the (simulated) line is free to carry it."""
        if self._ser is None:
            raise self._lost("port not open")
        if self.rate is not None:
            now = time.monotonic()
            start = max(now, self._free_at)
            self._free_at = start + len(data) / self.rate
            if start - now > 0.0005:
                await asyncio.sleep(start - now)
        if self._ser is None:
            raise self._lost("port closed")
        try:
            self._ser.write(data)
        except (serial.SerialException, OSError) as exc:
            self._error = str(exc)
            raise self._lost(f"write failed ({exc})") from None
        self.bytes_written += len(data)

    def close(self) -> None:
        self._stop.set()
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:
                pass
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self._thread = None
