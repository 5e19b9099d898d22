"""`AsyncRider`, the Rider for asyncio: each method is the blocking `Rider`'s, with its own
parameters and result type, run in a worker thread (its iterators fed to an async iterator by
a thread). Typed: mypy sees every method's real signature, and no `Any` comes out of them."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator, Awaitable, Callable, Iterable, Iterator
from pathlib import Path
from typing import Concatenate, Generic, ParamSpec, Self, TypedDict, TypeVar, Unpack, overload

from .blocking import Rider

P = ParamSpec("P")
R = TypeVar("R")
T = TypeVar("T")
F = TypeVar("F", bound=Callable[..., object])


class Options(TypedDict, total=False):
    """`Rider`'s keyword-only options (its docstring says what each does)."""

    connect: Iterable[str] | None
    zenoh_config_path: Path | None
    listen: Iterable[str] | None
    key_prefix: str
    timeout: float
    retries: int
    supervise: bool
    zenoh_threads: int


class Mirror(Generic[F]):
    """A `Rider` method as an `AsyncRider` method: read on an AsyncRider, it is `bind` of that
    AsyncRider's `sync` Rider (read on the class, the descriptor itself)."""

    def __init__(self, method: Callable[..., object]) -> None:
        self.__doc__ = method.__doc__
        self.name = getattr(method, "__name__", "")

    @overload
    def __get__(self, owner: None, kind: type[AsyncRider]) -> Self: ...

    @overload
    def __get__(self, owner: AsyncRider, kind: type[AsyncRider]) -> F: ...

    def __get__(self, owner: AsyncRider | None, kind: type[AsyncRider]) -> Self | F:
        if owner is None:
            return self
        bound = self.bind(owner.sync)
        bound.__name__, bound.__doc__ = self.name, self.__doc__
        return bound

    def bind(self, rider: Rider) -> F:
        raise NotImplementedError


class InThread(Mirror[Callable[P, Awaitable[R]]]):
    """A `Rider` method as a coroutine method: the same parameters and result, run in a worker
    thread (`asyncio.to_thread`)."""

    def __init__(self, method: Callable[Concatenate[Rider, P], R]) -> None:
        super().__init__(method)
        self.method = method

    def bind(self, rider: Rider) -> Callable[P, Awaitable[R]]:
        method = self.method

        async def call(*args: P.args, **kwargs: P.kwargs) -> R:
            return await asyncio.to_thread(method, rider, *args, **kwargs)

        return call


class StreamInThread(Mirror[Callable[P, AsyncIterator[T]]]):
    """A `Rider` method that returns an iterator as one that returns an async iterator: the
    same parameters, the iterator run on a thread of its own that feeds the event loop (and
    stops at its next item once the consumer or the loop has gone)."""

    def __init__(self, method: Callable[Concatenate[Rider, P], Iterator[T]]) -> None:
        super().__init__(method)
        self.method = method

    def bind(self, rider: Rider) -> Callable[P, AsyncIterator[T]]:
        method, name = self.method, f"rider-{self.name}"

        def call(*args: P.args, **kwargs: P.kwargs) -> AsyncIterator[T]:
            return _stream(lambda: method(rider, *args, **kwargs), name)

        return call


async def _stream(items: Callable[[], Iterator[T]], name: str) -> AsyncIterator[T]:
    """What `items()` yields on a thread named `name`, as an async iterator."""
    loop = asyncio.get_running_loop()
    out: asyncio.Queue[tuple[T] | None] = asyncio.Queue()
    stop = threading.Event()

    def deliver(item: tuple[T] | None) -> bool:
        """Hand `item` to the loop; False once the consumer or the loop itself is gone."""
        if stop.is_set() or loop.is_closed():
            return False
        try:
            loop.call_soon_threadsafe(out.put_nowait, item)
        except RuntimeError:  # the loop closed between the check and the call
            return False
        return True

    def pump() -> None:
        try:
            for item in items():
                if not deliver((item,)):
                    break
        finally:
            deliver(None)

    worker = threading.Thread(target=pump, name=name, daemon=True)
    worker.start()
    try:
        while (got := await out.get()) is not None:
            yield got[0]
    finally:
        stop.set()


class AsyncRider:
    """The same client for asyncio: blocking Zenoh calls run in a worker thread."""

    def __init__(self, machine_id: str | None = "m1", **options: Unpack[Options]) -> None:
        self.sync = Rider(machine_id, **options)
        """The blocking Rider underneath (its attributes: `timeout`, `login`, `base`, …)."""

    async def __aenter__(self) -> AsyncRider:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def open(self) -> AsyncRider:
        await asyncio.to_thread(self.sync.open)
        return self

    async def close(self) -> None:
        await asyncio.to_thread(self.sync.close)

    @property
    def rider_id(self) -> str:
        return self.sync.rider_id

    no_link_hint = InThread(Rider.no_link_hint)
    pick_machine = InThread(Rider.pick_machine)
    resolve_machine = InThread(Rider.resolve_machine)
    machines = InThread(Rider.machines)
    follow_machines = StreamInThread(Rider.follow_machines)
    holders = InThread(Rider.holders)

    new_transaction_id = InThread(Rider.new_transaction_id)
    command = InThread(Rider.command)
    calibrate_tilt = InThread(Rider.calibrate_tilt)
    calibrate_rotate = InThread(Rider.calibrate_rotate)
    home = InThread(Rider.home)
    start = InThread(Rider.start)
    pause = InThread(Rider.pause)
    resume = InThread(Rider.resume)
    stop = InThread(Rider.stop)
    check_calibration = InThread(Rider.check_calibration)
    check_home = InThread(Rider.check_home)

    status = InThread(Rider.status)
    io = InThread(Rider.io)
    axes = InThread(Rider.axes)
    diag = InThread(Rider.diag)
    validate = InThread(Rider.validate)
    calibration = InThread(Rider.calibration)
    set_calibration = InThread(Rider.set_calibration)
    params = InThread(Rider.params)
    param = InThread(Rider.param)
    set_param = InThread(Rider.set_param)
    reset_param = InThread(Rider.reset_param)
    sim = InThread(Rider.sim)

    event_pages = InThread(Rider.event_pages)
    events = InThread(Rider.events)
    events_summary = InThread(Rider.events_summary)
    follow_events = StreamInThread(Rider.follow_events)

    watch = StreamInThread(Rider.watch)
    subscribe = InThread(Rider.subscribe)

    done = InThread(Rider.done)
    recent_completions = InThread(Rider.recent_completions)
    wait_done = InThread(Rider.wait_done)
    wait_for = InThread(Rider.wait_for)
