"""Who asked, proven: what the machine's question to a Rider adds to a Start's round trip.

A Start that names a Rider runs only once that Rider has confirmed it sent it
(`rider/<login>/<zid>/confirm`, service/bus/confirm.py): one more round trip, machine → Rider →
machine, inside the Start's own. Measured on one daemon (simulator, 10 ms loop, calibrated and
homed) from this process over tcp/127.0.0.1, the variants interleaved Start by Start:

- a raw zenoh `get` on `cmd/start` that names no Rider: the machine asks nobody (the baseline:
  every Start took this path before the check);
- the same raw `get` naming this session as its Rider (the `rider` field and the attachment),
  with a queryable that confirms it: the check's whole cost, nothing else changed;
- `Rider.start()` (the library an operator's tools use), which names itself and confirms.

Each Start is stopped at once and the next waits for IDLE. Times are the reply's round trip.
"""

from __future__ import annotations

import contextlib
import itertools
import sys
import time
from collections.abc import Callable, Iterator

import zenoh

from bench.common import Dist, Options, Section, Table, Target, main_for, ms, only_reply
from bench.daemon import bench_daemon, home_and_start
from ride_machine.rider.client import Rider
from ride_machine.rider.confirm import Confirmations, Ledger
from ride_machine.rider.errors import CommandRefused
from ride_machine.rider.link import zenoh_config
from ride_machine.schema.codec import Format, decode, encode
from ride_machine.schema.commands import Reply, StartRequest
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.rider import rider_id
from ride_machine.schema.status import MachineState
from tests.procs import Daemon

HOME_TRIES = 3
AT_REST = [MachineState.IDLE, MachineState.DONE, MachineState.WARNING_NOT_HOME]
BARE = "raw get, no Rider named (nobody asked)"
CLAIMED = "raw get naming its Rider, confirmed"
LIBRARY = "Rider.start() (names itself, confirmed)"
VARIANTS = (BARE, CLAIMED, LIBRARY)


class Raw:
    """A plain session that sends Starts by hand, with or without naming itself."""

    def __init__(self, daemon: Daemon) -> None:
        self.session = zenoh.open(zenoh_config(daemon.zenoh_config, [daemon.endpoint]))
        self.key = f"machine/{daemon.machine_id}/cmd/start"
        self.rider = rider_id("anonymous", str(self.session.zid()))
        self.ledger = Ledger()
        self.confirmations = Confirmations(self.session, self.rider, self.ledger)
        self._ids = itertools.count()

    def start(self, claim: bool) -> tuple[float, Reply]:
        request = StartRequest(
            transaction_id=f"bench-confirm-{next(self._ids)}",
            timecode=time.time(),
            valid_for=10.0,
            rider=self.rider if claim else None,
        )
        payload = encode(request)
        attachment = f"rider={self.rider}".encode() if claim else None
        if claim:
            self.ledger.sent(payload)
        began = time.perf_counter()
        replies = list(
            self.session.get(self.key, payload=payload, attachment=attachment, timeout=5.0)
        )
        took = time.perf_counter() - began
        return took, decode(Reply, only_reply(replies, self.key), Format.MSGPACK)

    def close(self) -> None:
        self.confirmations.close()
        self.session.close()  # type: ignore[no-untyped-call]


@contextlib.contextmanager
def raw(daemon: Daemon) -> Iterator[Raw]:
    session = Raw(daemon)
    try:
        yield session
    finally:
        session.close()


def timed_library(rider: Rider) -> tuple[float, Reply]:
    began = time.perf_counter()
    reply = rider.start()
    return time.perf_counter() - began, reply


def accepted(rider: Rider, start: Callable[[], tuple[float, Reply]], variant: str) -> float:
    """The round trip of a Start the machine took: one refused because the Stop before it left
    an axis off home (the ride had begun to move) is not timed; the machine homes, and the
    Start goes again."""
    for _ in range(HOME_TRIES):
        rider.wait_for(AT_REST, timeout=30.0)
        try:
            took, reply = start()
        except CommandRefused as exc:  # the library raises what the raw get returns
            took, reply = 0.0, exc.reply
        if reply.success:
            return took
        if reply.error is None or reply.error.code is not ErrorCode.NOT_HOME:
            raise RuntimeError(f"{variant}: Start refused: {reply.error}")
        home = rider.home()
        rider.wait_for([MachineState.IDLE], timeout=60.0, after=home.timecode)
    raise RuntimeError(f"{variant}: the machine would not stay home")


ADDED_LIMIT_S = 0.001
"""Our bound for the confirmation's cost on loopback: one query round trip, well under the
heartbeat period (0.1 s) the ride's supervision already works at."""


def run(opts: Options) -> Section:
    rounds = opts.pick(10, 150, 600)
    samples: dict[str, list[float]] = {v: [] for v in VARIANTS}
    with bench_daemon(calibrated=True) as daemon, daemon.rider(timeout=5.0) as rider:
        home_and_start(rider)
        rider.stop()
        with raw(daemon) as plain:
            ways: dict[str, Callable[[], tuple[float, Reply]]] = {
                BARE: lambda: plain.start(False),
                CLAIMED: lambda: plain.start(True),
                LIBRARY: lambda: timed_library(rider),
            }
            for _ in range(rounds):
                for variant in VARIANTS:
                    samples[variant].append(accepted(rider, ways[variant], variant))
                    rider.stop()
    table = Table(
        "Start's round trip, with and without the Rider's confirmation",
        ["variant", "n", "p50", "p90", "p99", "max"],
        note="interleaved Start by Start on one daemon; each Start stopped at once",
    )
    dists = {v: Dist.of(s) for v, s in samples.items()}
    for variant, d in dists.items():
        table.add(variant, d.n, ms(d.p50), ms(d.p90), ms(d.p99), ms(d.max))
    added = dists[CLAIMED].p50 - dists[BARE].p50
    return Section(
        "confirm",
        "Who asked: the Start's round trip",
        tables=[table],
        targets=[
            Target.at_most("what the check adds to a raw Start's p50", added, ADDED_LIMIT_S, ms)
        ],
        notes=[
            f"The check adds {ms(added)} to the p50 of a raw Start"
            f" ({ms(dists[BARE].p50)} → {ms(dists[CLAIMED].p50)}): the machine's query to the"
            " Rider and its answer, on loopback."
        ],
    )


if __name__ == "__main__":
    sys.exit(main_for("bench.confirm", __doc__ or "", run))
