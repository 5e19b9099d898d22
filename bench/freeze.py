"""A frozen daemon: from the freeze to the ride's relays off, and how far the tilt overran.

Under `machine supervise --sim` as the README runs it (no --zenoh-config: Zenoh's 10 s lease),
with the project's defaults (10 ms period, watchdog limit 0.1 s), the daemon drives the tilt
towards 45° at its nominal 15°/s and is frozen 5° into the move, each trial one of three ways:
SIGSTOP (every thread stops), its scan thread holding the GIL for ever, or its scan thread
blocked in a system call (tests/fixtures/freeze). The time is from the signal to the process
image showing every relay off (read every 0.2 ms); the overrun is the simulator's tilt travel
past where it was at the signal. Each kind runs on a quiet host and beside one CPU-bound
process per core (bench/baselines/burner.py), the phases alternated.

Then the whole controller frozen at once (tests/freeze_whole.py): the supervisor, its daemon
and the daemon's history process stopped by SIGSTOP, or frozen in a freezer cgroup of their own
(what `docker pause` / `podman pause` do), for 1.5 s mid-move, while the simulated plant runs on
in a process of its own. The time is from the freeze to the plant's charge-pump relay cutting
the drives (`hal.sim.charge_pump_timeout_s`, 0.1 s), read from the plant; the same freeze of a
ride without a charge pump beside it (the old behaviour: relays on, drives powered, the whole
freeze).

Then the stall soak: an idle, homed daemon (the same defaults, under the supervisor) beside
one CPU-bound process per core for ten minutes: its stalls, their longest, and its faults.
"""

from __future__ import annotations

import contextlib
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from bench import common
from bench.common import Dist, Options, Section, Table, Target, main_for, ms
from ride_machine.schema.status import FAULT_STATES
from ride_machine.sim.settings import PhysicsParams
from tests.freeze import (
    LIMIT_S,
    PERIOD_S,
    Freeze,
    Outcome,
    ride_and_freeze,
    supervised,
)
from tests.freeze_whole import FreezerCgroup, Whole, WholeOutcome, freeze_whole
from tests.integration.support import prepare

BOUND_S = LIMIT_S + 2 * PERIOD_S
"""The issue's target: relays off within the watchdog limit plus two periods."""
PUMP_TIMEOUT_S = PhysicsParams().charge_pump_timeout_s
WHOLE_HOLD_S = 1.5
"""How long each whole-controller freeze lasts: past the supervisor's 1 s `--hang`, so it
replaces the frozen daemon once it runs again (the relay acts within a tenth of it)."""


@contextlib.contextmanager
def burners(tmp: Path, on: bool, seconds: float) -> Iterator[None]:
    """One CPU-bound process per core for the block (none when `on` is False)."""
    with common.burners(2 if on else 0, tmp, seconds + 120.0):
        yield


def trials(n: int, tmp: Path, loads: tuple[bool, ...]) -> dict[tuple[Freeze, bool], list[Outcome]]:
    """`n` freezes of each kind on each host (`loads`: quiet False, beside burners True), the
    phases alternated in rounds."""
    results: dict[tuple[Freeze, bool], list[Outcome]] = {
        (k, load): [] for k in Freeze for load in loads
    }
    with supervised(tmp, timeout=5.0, ready_s=60.0) as (supervisor, rider):
        for i in range(n):
            for load in loads if i % 2 == 0 else loads[::-1]:
                with burners(tmp, load, 60.0):
                    for kind in Freeze:
                        results[kind, load].append(ride_and_freeze(supervisor, rider, kind))
    return results


WholeKey = tuple[Whole, bool, bool]
"""(freeze, beside burners, with a charge pump)."""


def whole_trials(
    n: int, baseline: int, tmp: Path, loads: tuple[bool, ...]
) -> dict[WholeKey, list[WholeOutcome]]:
    """`n` whole-controller freezes of each kind on each host with a charge pump, `baseline`
    of each without (a supervisor of its own each), the loads alternated in rounds."""
    kinds = [k for k in Whole if k is not Whole.CGROUP or FreezerCgroup.unavailable() is None]
    results: dict[WholeKey, list[WholeOutcome]] = {}
    for pump, count in ((True, n), (False, baseline)):
        with supervised(tmp / f"whole-{pump}", pump=pump, timeout=5.0, ready_s=60.0) as (
            supervisor,
            rider,
        ):
            for i in range(count):
                for load in loads if i % 2 == 0 else loads[::-1]:
                    with burners(tmp, load, 60.0):
                        for kind in kinds:
                            outcome = freeze_whole(supervisor, rider, kind, WHOLE_HOLD_S)
                            results.setdefault((kind, load, pump), []).append(outcome)
    return results


def whole_table(results: dict[WholeKey, list[WholeOutcome]]) -> tuple[Table, float]:
    """The whole-controller table, and the longest cut with a charge pump (inf: one never)."""
    table = Table(
        "The whole controller frozen (supervisor, daemon, history): from the freeze to the"
        " drives without power, read from the simulated plant",
        [
            "freeze",
            "host",
            "charge pump",
            "trials",
            "p50 ms",
            "p99 ms",
            "max ms",
            "tilt overrun p50 °",
            "max °",
            "relays on at the end",
        ],
        note=f"each freeze {WHOLE_HOLD_S:g} s, 5° into a move at 15°/s; the relay drops"
        f" {PUMP_TIMEOUT_S * 1e3:g} ms after the pump's last change; without a charge pump"
        " nothing acts until the controller runs again",
    )
    worst = 0.0
    for (kind, load, pump), outcomes in sorted(results.items(), key=lambda kv: (not kv[0][2],)):
        cuts = [o.cut_s for o in outcomes if o.cut_s is not None]
        d, over = Dist.of(cuts), Dist.of([o.overrun_deg for o in outcomes])
        never = len(outcomes) - len(cuts)
        if pump:
            worst = max([worst, *cuts]) if not never else float("inf")
        on = sum(o.relays_on for o in outcomes)
        table.add(
            str(kind),
            "2 burners" if load else "quiet",
            f"yes, {PUMP_TIMEOUT_S * 1e3:g} ms" if pump else "no (before)",
            f"{len(outcomes)}" + (f" ({never} powered throughout)" if never else ""),
            ms(d.p50, 1) if cuts else "never",
            ms(d.p99, 1) if cuts else "never",
            ms(d.max, 1) if cuts else "never",
            f"{over.p50:.2f}",
            f"{over.max:.2f}",
            f"{on} of {len(outcomes)}",
        )
    return table, worst


def soak(seconds: float, tmp: Path, load: bool) -> tuple[float, int, float, int, int, str]:
    """An idle, homed daemon (beside a burner per core with `load`): (seconds, stalls, longest
    stall s, watchdog trips, fault states seen, its final state)."""
    faults = 0
    with (
        supervised(tmp / "soak", timeout=5.0, ready_s=60.0) as (_, rider),
        burners(tmp, load, seconds),
    ):
        prepare(rider)
        before = rider.diag(reset=True)
        t0 = time.monotonic()
        deadline = t0 + seconds
        state = rider.status().state
        while time.monotonic() < deadline:
            time.sleep(min(1.0, max(0.0, deadline - time.monotonic())))
            state = rider.status().state
            faults += state in FAULT_STATES
        after = rider.diag()
        elapsed = time.monotonic() - t0
    del before
    return elapsed, after.stalls, after.longest_stall_s, after.watchdog_trips, faults, str(state)


def run(opts: Options) -> Section:
    n = opts.pick(1, 20, 40)
    soak_s = opts.pick(5.0, 600.0, 1800.0)
    # The smoke run (beside the other benchmarks' smoke runs) starts no CPU burners.
    loads = opts.pick((False,), (False, True))
    section = Section(
        "freeze", "13. A frozen daemon, a frozen controller: relays off, drives unpowered"
    )
    with tempfile.TemporaryDirectory(prefix="bench-freeze-") as name:
        tmp = Path(name)
        (tmp / "soak").mkdir()
        results = trials(n, tmp, loads)
        whole = whole_trials(n, opts.pick(1, 5, 10), tmp, loads)
        soaked = soak(soak_s, tmp, load=loads[-1])
    table = Table(
        "From the freeze to every relay off in the process image (the supervisor's output guard)",
        ["freeze", "host", "trials", "p50 ms", "p99 ms", "max ms", "tilt overrun p50 °", "max °"],
        note=f"watchdog limit {LIMIT_S * 1e3:g} ms, period {PERIOD_S * 1e3:g} ms; tilt 15°/s;"
        " no --zenoh-config (the 10 s lease the relays waited for before)",
    )
    worst = 0.0
    for (kind, load), outcomes in results.items():
        off = [o.off_s for o in outcomes if o.off_s is not None]
        over = [o.overrun_deg for o in outcomes if o.overrun_deg is not None]
        d, o = Dist.of(off), Dist.of(over)
        missing = len(outcomes) - len(off)
        worst = max([worst, *off]) if not missing else float("inf")
        table.add(
            str(kind),
            "2 burners" if load else "quiet",
            f"{len(outcomes)}" + (f" ({missing} never off)" if missing else ""),
            ms(d.p50, 1),
            ms(d.p99, 1),
            ms(d.max, 1),
            f"{o.p50:.2f}",
            f"{o.max:.2f}",
        )
    section.tables.append(table)
    table, worst_cut = whole_table(whole)
    section.tables.append(table)
    elapsed, stalls, longest, trips, faults, state = soaked
    beside = "beside a CPU-bound process per core" if loads[-1] else "on a quiet host"
    idle = Table(
        f"An idle, homed daemon under the supervisor {beside}",
        ["seconds", "stalls over the limit", "longest stall ms", "watchdog trips", "fault states"],
        note=f"its state at the end: {state}",
    )
    idle.add(f"{elapsed:.0f}", stalls, ms(longest, 1), trips, faults)
    section.tables.append(idle)
    section.targets.append(
        Target.at_most("freeze → relays off, every trial", worst, BOUND_S, lambda v: ms(v, 1))
    )
    section.targets.append(
        Target.at_most(
            "whole controller frozen → drives without power, every trial",
            worst_cut,
            PUMP_TIMEOUT_S + 2 * PERIOD_S,
            lambda v: ms(v, 1),
        )
    )
    section.targets.append(
        Target(f"idle {beside}: no fault", "0", str(faults + trips), faults + trips == 0)
    )
    return section


if __name__ == "__main__":
    sys.exit(main_for("bench.freeze", __doc__ or "", run))
