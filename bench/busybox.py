"""A busy box is a normal box: Homes and sessions on one core shared with two CPU-bound
processes, with and without SCHED_FIFO (issue 59).

A Revolution Pi usually runs other things beside the ride. Here the whole daemon is pinned to
one core (`loop.cpus`) and two CPU-bound neighbours (bench/baselines/burner.py) are pinned to
the same core: the stand-in for a loaded Pi. The machine runs the project's default timing (a
10 ms scan, the watchdog at 3 periods) and mechanics; the Rider runs on the other core, as a
station would on its own computer. Each round is a Home, then a session (tilt 10°, one
revolution); every outcome is counted: DONE, each fault by its code, each refusal
by its code. Without a real-time class the neighbours take the core for whole time slices and
the scan misses its watchdog; with `loop.rt_priority` the kernel runs the scan thread first.
Run alone with `python -m bench.busybox` (100 rounds each way: about 25 minutes).
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

from bench.common import Options, Section, Table, Target, burners, main_for
from bench.daemon import Tuning, bench_daemon, pinnable_cpu
from ride_machine.rider.client import CommandRefused, Rider
from ride_machine.rider.errors import MachineTimeout
from ride_machine.schema.commands import Reply, RotateStep, Session, TiltStep
from ride_machine.schema.status import MachineState, Status

PRIORITY = 50
SESSION = Session(
    name="busybox",
    steps=[TiltStep(degrees=10.0), RotateStep(revolutions=1)],
)
SETTLED = {
    MachineState.IDLE,
    MachineState.DONE,
    MachineState.PAUSED,  # the Rider was lost: its station starved
    MachineState.FAULT_HW,
    MachineState.FAULT_ESTOP,
    MachineState.WARNING_NOT_HOME,
    MachineState.WARNING_NEEDS_CALIBRATION,
}
WAIT_S = 60.0


@contextlib.contextmanager
def neighbours(core: int, tmp: Path, seconds: float) -> Iterator[None]:
    """Two CPU-bound processes pinned to `core` for the block."""
    with burners(2, tmp, seconds) as started:
        for burner in started:
            os.sched_setaffinity(burner.pid, {core})
        yield


def outcome(rider: Rider, ask: Reply | None, refused: CommandRefused | None) -> str:
    """What one Home or session came to: DONE/IDLE, `fault <code>` or `refused <code>`."""
    if refused is not None:
        code = refused.reply.error.code.value if refused.reply.error else "?"
        return f"refused {code}"
    assert ask is not None
    try:
        status = settle(rider, ask.timecode)
    except MachineTimeout as exc:
        return f"no end within {WAIT_S:g} s ({exc})"
    if status.fault is not None:
        return f"fault {status.fault.code.value}"
    return status.state.value


def settle(rider: Rider, after: float) -> Status:
    return rider.wait_for(SETTLED, timeout=WAIT_S, after=after)


def attempt(rider: Rider, command: str) -> str:
    try:
        reply = rider.home() if command == "Home" else rider.start(SESSION)
    except CommandRefused as exc:
        return outcome(rider, None, exc)
    return outcome(rider, reply, None)


def rounds(tuning: Tuning, n: int, core: int, tmp: Path) -> Counter[str]:
    """`n` Homes and `n` sessions on a daemon pinned beside two neighbours; outcomes counted
    per command (`Home: IDLE`, `Start: fault TILT_NOT_FOLLOWING`, …)."""
    counts: Counter[str] = Counter()
    with (
        bench_daemon(tuning=tuning, calibrated=True) as daemon,
        neighbours(core, tmp, seconds=n * 30.0 + 120.0),
        daemon.rider(timeout=5.0) as rider,
    ):
        for _ in range(n):
            for command in ("Home", "Start"):
                counts[f"{command}: {attempt(rider, command)}"] += 1
            if rider.status().state in {MachineState.FAULT_HW, MachineState.PAUSED}:
                rider.stop()  # clears it for the next round's Home
    return counts


def is_false_fault(key: str) -> bool:
    """A fault on a healthy simulated machine: everything that is not DONE or IDLE."""
    return not key.endswith((": DONE", ": IDLE"))


def run(opts: Options) -> Section:
    n = opts.pick(2, 100, 300)
    cpus = os.sched_getaffinity(0)
    core = pinnable_cpu()
    if core is None:
        raise SystemExit("bench.busybox needs two cores: one for the machine, one for the Rider")
    os.sched_setaffinity(0, cpus - {core})  # the Rider (this process) off the loaded core
    variants = {
        "SCHED_OTHER (no rt_priority)": Tuning(cpus=(core,)),
        f"SCHED_FIFO {PRIORITY} (rt_priority)": Tuning(cpus=(core,), rt_priority=PRIORITY),
    }
    results: dict[str, Counter[str]] = {}
    with tempfile.TemporaryDirectory(prefix="busybox-") as tmp:
        for label, tuning in variants.items():
            results[label] = rounds(tuning, n, core, Path(tmp))
    os.sched_setaffinity(0, cpus)
    table = Table(
        f"Outcomes of {n} Homes and {n} sessions on one core beside two CPU-bound processes",
        ["variant", "outcome", "count"],
        note="the machine's default timing (10 ms scan, watchdog 3 periods); a session is tilt"
        " 10° and one revolution",
    )
    for label, counts in results.items():
        for key, count in sorted(counts.items()):
            table.add(label, key, count)
    fifo = results[f"SCHED_FIFO {PRIORITY} (rt_priority)"]
    false = sum(c for k, c in fifo.items() if is_false_fault(k))
    return Section(
        "busybox",
        "A busy box: Homes and sessions on a loaded core",
        tables=[table],
        targets=[
            Target(
                f"false faults and refusals with rt_priority ({2 * n} commands)",
                "0",
                str(false),
                false == 0,
                "" if false == 0 else f"{false} of {2 * n}",
            )
        ],
        notes=[
            f"Core {core} carries the daemon and two CPU-bound processes; the Rider runs on the"
            " other. A false fault is any outcome but DONE (a session) or IDLE (a Home)."
        ],
    )


if __name__ == "__main__":
    sys.exit(main_for("bench.busybox", __doc__ or "", run))
