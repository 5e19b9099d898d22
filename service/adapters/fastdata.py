"""The FastData UDP server: answers an axis mask with one packed `serverdata` reply.

It runs on its own thread and only reads the loop's published snapshot (a dict the loop
replaces whole), so no request can block, slow down with a lock, or queue work for the loop.
"""

from __future__ import annotations

import contextlib
import logging
import selectors
import socket
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from ride_machine.schema.axes import AxisRecord, PnStatus
from ride_machine.schema.fastdata import (
    DEFAULT_PORT,
    MAX_REQUEST_BYTES,
    SERVERDATA_VERSION,
    USER_REGISTER_LENGTH,
    FastAxisData,
    encode,
)
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.threads import NamedThread

log = logging.getLogger(__name__)

DEFAULT_MAX_RATE = 2000.0
"""Requests handled per second, at most; beyond it the kernel queues, then drops, the excess.

Each request costs the server thread ~30 µs of the interpreter lock that the scan thread also
needs, so an unbounded storm would add wake-up jitter to a 1 ms loop.
"""
DRV_STAT_FAULT = 1
"""`drvStat` of an axis whose drive-fault bit is set; 0 otherwise."""

_U32 = 0xFFFFFFFF

Snapshot = Callable[[], Mapping[str, AxisRecord]]


@dataclass(frozen=True)
class UserRegisters:
    """Version 1's user data: `USER_REGISTER_LENGTH` int32s and doubles set by the operator."""

    ints: tuple[int, ...] = (0,) * USER_REGISTER_LENGTH
    doubles: tuple[float, ...] = (0.0,) * USER_REGISTER_LENGTH

    @classmethod
    def of(cls, ints: Sequence[int], doubles: Sequence[float]) -> UserRegisters:
        """Padded with zeros (or cut) to exactly `USER_REGISTER_LENGTH` each."""
        n = USER_REGISTER_LENGTH
        return cls(
            tuple(ints[:n]) + (0,) * (n - len(ints[:n])),
            tuple(float(d) for d in doubles[:n]) + (0.0,) * (n - len(doubles[:n])),
        )


Registers = Callable[[], UserRegisters]


def user_registers(config: MachineConfig) -> UserRegisters:
    """The registers as the (live, online-parameter) config holds them."""
    return UserRegisters.of(config.fastdata.user_ints, config.fastdata.user_doubles)


def to_fast_axis(record: AxisRecord, cycle: int | None = None) -> FastAxisData:
    """Our axis record as `FastAxisData`; quantities the ride has no sensor for are 0.0.

    `cCmd`/`cFb` are the position in drive units (tilt: raw analog counts; rotate: turns)."""
    status = record.pn_status & _U32
    return FastAxisData(
        pnStatus=status,
        axisnumber=record.axis_number,
        drvStat=DRV_STAT_FAULT if status & PnStatus.DRIVE_FAULT else 0,
        bus_cycle_num=(record.cycle if cycle is None else cycle) & _U32,
        pCmd=record.position_cmd,
        pFb=record.position_fb,
        pExt=0.0,
        cCmd=record.drive_cmd,
        cFb=record.drive_fb,
        vCmd=record.velocity_cmd,
        vFb=record.velocity_fb,
        aCmd=0.0,
        tAddCmd=0.0,
        tFb=0.0,
    )


def build_reply(
    mask: bytes,
    axes: Mapping[str, AxisRecord],
    cycle: int | None = None,
    registers: UserRegisters | None = None,
) -> bytes:
    """The reply to one axis mask: the wanted axes that exist, by ascending axis number.

    As in seed 002, request cell i asks for axis number i + 1. `int_array` and `double_array`
    carry the user registers, always `USER_REGISTER_LENGTH` long.
    """
    by_number: dict[int, AxisRecord] = {}
    for name in sorted(axes):
        record = axes[name]
        by_number.setdefault(record.axis_number, record)
    wanted = [
        to_fast_axis(by_number[n], cycle)
        for n in sorted(by_number)
        if 0 <= n - 1 < len(mask) and mask[n - 1]
    ]
    regs = registers or UserRegisters()
    return encode(wanted, SERVERDATA_VERSION, ints=regs.ints, doubles=regs.doubles)


def valid_mask(request: bytes) -> bool:
    """A request is a non-empty axis mask of at most `MAX_REQUEST_BYTES` bytes."""
    return 0 < len(request) <= MAX_REQUEST_BYTES


class RequestBudget:
    """A token bucket: `rate` requests per second, bursts of up to `burst`."""

    def __init__(self, rate: float, burst: float, clock: Callable[[], float]) -> None:
        if rate <= 0 or burst < 1:
            raise ValueError("a request budget needs rate > 0 and burst >= 1")
        self.rate = rate
        self.burst = burst
        self.clock = clock
        self.tokens = burst
        self._last = clock()

    def take(self) -> float:
        """0.0 and one token spent if a request may run now, else the seconds until one may."""
        now = self.clock()
        self.tokens = min(self.burst, self.tokens + (now - self._last) * self.rate)
        self._last = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return 0.0
        return (1.0 - self.tokens) / self.rate


@dataclass
class FastDataStats:
    """Counters, written only by the server thread."""

    requests: int = 0
    replies: int = 0
    ignored: int = 0
    errors: int = 0
    throttled: int = 0
    """Times the server paused reading because requests came faster than `max_rate`."""


class FastDataServer:
    """UDP FastData server on its own thread; `start()` binds (errors surface there), `close()`."""

    def __init__(
        self,
        snapshot: Snapshot,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        cycle: Callable[[], int] | None = None,
        *,
        max_rate: float = DEFAULT_MAX_RATE,
        registers: Registers | None = None,
    ) -> None:
        self.snapshot = snapshot
        self.cycle = cycle
        self.registers = registers
        self.budget = RequestBudget(max_rate, max(1.0, max_rate / 20), time.monotonic)
        self.host = host
        self.stats = FastDataStats()
        self._port = port
        self._sock: socket.socket | None = None
        self._wake_r, self._wake_w = socket.socketpair()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        """The bound port (the ephemeral one when constructed with port 0)."""
        return self._port

    @property
    def address(self) -> tuple[str, int]:
        return (self.host, self._port)

    def start(self) -> None:
        """Bind and start answering; raises `OSError` if the address cannot be bound."""
        if self._thread is not None:
            raise RuntimeError("FastDataServer already started")
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.bind((self.host, self._port))
        except OSError:
            sock.close()
            raise
        sock.setblocking(False)
        self._sock = sock
        self._port = sock.getsockname()[1]
        self._thread = NamedThread(target=self._serve, name="fastdata", daemon=True)
        self._thread.start()
        log.info("event=fastdata_listening host=%s port=%d", self.host, self._port)

    def close(self, timeout: float = 2.0) -> None:
        """Stop the thread (bounded by `timeout`) and release the socket; safe to call twice."""
        self._stop.set()
        with contextlib.suppress(OSError):  # already closed: the thread was told before
            self._wake_w.send(b"x")
        thread = self._thread
        if thread is not None:
            thread.join(timeout)
            if thread.is_alive():
                log.warning("event=fastdata_close_timeout timeout_s=%s", timeout)
                return  # the thread still owns the sockets; it is a daemon and dies with us
        for s in (self._sock, self._wake_r, self._wake_w):
            if s is not None:
                s.close()

    def __enter__(self) -> FastDataServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _serve(self) -> None:
        sock = self._sock
        assert sock is not None
        with selectors.DefaultSelector() as sel:
            sel.register(sock, selectors.EVENT_READ)
            sel.register(self._wake_r, selectors.EVENT_READ)
            while not self._stop.is_set():
                for key, _ in sel.select():
                    if key.fileobj is sock:
                        self._drain(sock)

    def _drain(self, sock: socket.socket) -> None:
        """Answer every datagram waiting; one bad one never stops the others."""
        while not self._stop.is_set():
            try:
                # One byte more than allowed, so an oversize request is seen as oversize.
                request, peer = sock.recvfrom(MAX_REQUEST_BYTES + 1)
            except BlockingIOError:
                return
            except OSError as exc:  # e.g. ICMP errors reported on the socket: not fatal
                self.stats.errors += 1
                log.debug("event=fastdata_recv_error error=%r", exc)
                return
            self.stats.requests += 1
            self._pace()
            if not valid_mask(request):
                self.stats.ignored += 1
                continue
            try:
                regs = self.registers() if self.registers is not None else None
                reply = build_reply(request, self.snapshot(), self._cycle(), regs)
                sock.sendto(reply, peer)
                self.stats.replies += 1
            except OSError as exc:  # a full send buffer or an unroutable peer drops one reply
                self.stats.errors += 1
                log.debug("event=fastdata_send_error peer=%s error=%r", peer, exc)
            except Exception:  # a bad snapshot must not kill the server thread; logged below
                self.stats.errors += 1
                if self.stats.errors % 1000 == 1:  # a persistent fault must not flood the log
                    log.exception(
                        "event=fastdata_reply_failed peer=%s errors=%d", peer, self.stats.errors
                    )

    def _pace(self) -> None:
        """Spend a token; when none is left, stop reading until one is (close() cuts it short)."""
        wait = self.budget.take()
        if wait:
            self.stats.throttled += 1
            self._stop.wait(wait)
            self.budget.take()

    def _cycle(self) -> int | None:
        return None if self.cycle is None else self.cycle()
