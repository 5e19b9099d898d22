"""Default-machine lookup: what `rider status` without `--machine` costs over naming the machine.

One daemon; each sample opens a fresh Rider session (not timed) and times its first `status()`:
with the machine named (the baseline: no lookup), without it (the read lookup, 0.15 s settle),
and a command-grade lookup (`resolve_machine(motion=True)`, 0.3 s settle) — rider/discovery.py.
Then a site (tests/site: the router stand-in, daemon `a` a peer linked to it): the lookup from a
Rider on a's own port, which must also ask the router behind `a` (a short client session), and
from a client of the router.
"""

from __future__ import annotations

import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from bench.common import Dist, Options, Section, Table, Target, main_for, ms
from bench.daemon import bench_daemon
from ride_machine.rider.client import Rider
from tests.site.stand import PEER_CONFIG, site


def _timed(make: Callable[[], Rider], act: Callable[[Rider], object], n: int) -> Dist:
    samples = []
    for _ in range(n):
        with make() as rider:
            start = time.perf_counter()
            act(rider)
            samples.append(time.perf_counter() - start)
    return Dist.of(samples)


def run(opts: Options) -> Section:
    section = Section("pick", "Default-machine lookup (no --machine) vs --machine")
    n = opts.pick(3, 30, 100)
    with bench_daemon() as daemon:

        def named() -> Rider:
            return daemon.rider(supervise=False)

        def default() -> Rider:
            return Rider(None, connect=[daemon.endpoint], zenoh_config_path=daemon.zenoh_config)

        rows = [
            ("`--machine m1`, first status (baseline)", _timed(named, Rider.status, n)),
            ("no `--machine`, first status (read lookup)", _timed(default, Rider.status, n)),
            (
                "no `--machine`, command-grade lookup only",
                _timed(default, lambda r: r.resolve_machine(motion=True), n),
            ),
        ]
    rows += _site_rows(n)
    table = Table(
        "First call of a fresh Rider session, one daemon on tcp/127.0.0.1",
        ["what", "n", "p50 ms", "p90 ms", "max ms"],
    )
    for label, d in rows:
        table.add(label, d.n, ms(d.p50, 1), ms(d.p90, 1), ms(d.max, 1))
    section.tables.append(table)
    extra = rows[1][1].p50 - rows[0][1].p50
    section.targets.append(
        Target.at_most(
            "added latency of a read lookup, p50", extra, 0.25, lambda x: f"{ms(x, 1)} ms"
        )
    )
    return section


def _site_rows(n: int) -> list[tuple[str, Dist]]:
    """The lookup on a site: through a peer daemon's port (asks the router behind it) and as a
    client of the router."""
    with tempfile.TemporaryDirectory(prefix="bench-pick-") as tmp, site(Path(tmp)) as stand:
        stand.start_daemons({"a": "peer"})
        a = stand.daemons["a"]

        def on_a() -> Rider:
            return Rider(None, connect=[a.endpoint], zenoh_config_path=PEER_CONFIG)

        def on_router() -> Rider:
            return stand.rider(None)

        def read(r: Rider) -> object:
            return r.resolve_machine()

        def command(r: Rider) -> object:
            return r.resolve_machine(motion=True)

        return [
            ("site: peer on a's port, read lookup (asks the router)", _timed(on_a, read, n)),
            ("site: peer on a's port, command-grade lookup", _timed(on_a, command, n)),
            ("site: client of the router, read lookup", _timed(on_router, read, n)),
            ("site: client of the router, command-grade lookup", _timed(on_router, command, n)),
        ]


if __name__ == "__main__":
    sys.exit(main_for("bench.pick", __doc__ or "", run))
