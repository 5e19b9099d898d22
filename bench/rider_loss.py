"""Rider loss: how fast the machine pauses when its supervising Rider is SIGKILLed, SIGSTOPped or
cut off (veth down), and what the deadman heartbeat costs the daemon.

Detection: a daemon (fast simulator, 10 ms loop, `rider_loss.timeout_s` 0.5 s) runs a long
session; each trial a new Rider process on Zenoh's defaults (no --zenoh-config: a 10 s lease)
starts or resumes it, then fails one way. The time is the PAUSED status's own stamp (the cycle
that paused) minus the wall time of the failure, both on this host's clock. With root the daemon
and an observer sit in one network namespace and the Riders in another, joined by a veth pair
(so the link can be cut); without root everything runs on loopback and veth is skipped.

Cost: the daemon's CPU (% of one core) and scan-loop jitter with no Rider and with 3
supervising Riders (each putting its heartbeat every 0.1 s), phases interleaved in one run.
"""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from bench.common import CpuMeter, Dist, Options, Section, Table, Target, main_for, ms
from bench.daemon import bench_daemon, calibration_file
from ride_machine.service.core.storage.persist import CALIBRATION_FILE
from tests.integration.support import write_fast_config
from tests.netns import NetnsUnavailable, NsPair, veth_pair
from tests.procs import REPO, Daemon, LineReader, free_port, start_daemon, stop_process

TIMEOUT_S = 0.5
PERIOD_S = 0.010
KINDS = ("SIGKILL", "SIGSTOP", "veth down")

RIDER_CHILD = """
import sys
from ride_machine.rider.client import Rider
from ride_machine.schema.commands import RotateStep, Session, TiltStep
endpoint, action = sys.argv[1], sys.argv[2]
with Rider("m1", connect=[endpoint]) as r:  # Zenoh's defaults: a 10 s lease
    if action == "idle":
        print("ready", flush=True)
        sys.stdin.read()
        raise SystemExit(0)
    if action == "start":
        steps = [TiltStep(degrees=45.0), RotateStep(revolutions=1000)]
        reply = r.start(Session(name="bench", steps=steps))
    else:
        reply = r.resume()
    print("moving", reply.timecode, flush=True)
    sys.stdin.read()
"""

OBSERVER_CHILD = """
import json, sys
from ride_machine.rider.client import Rider
from ride_machine.schema.status import MachineState as S, Status
endpoint = sys.argv[1]
with Rider("m1", connect=[endpoint], supervise=False, timeout=5.0) as r:
    reply = r.home()
    r.wait_for({S.IDLE}, 60, after=reply.timecode)
    print("ready", flush=True)
    last = None
    for u in r.watch(("status",)):
        if isinstance(u, Status) and u.state != last:
            last = u.state
            print(json.dumps({"state": str(u.state), "time": u.time}), flush=True)
"""


@dataclass
class Setup:
    """Where the daemon and the Riders run: `rider_ns`/`machine_ns` None = this namespace."""

    endpoint: str
    rider_ns: str | None
    machine_ns: str | None
    pair: NsPair | None

    def wrap(self, ns: str | None, cmd: list[str]) -> list[str]:
        return ["ip", "netns", "exec", ns, *cmd] if ns else cmd


class Proc:
    """A child with stdin and line-by-line stdout (bounded reads)."""

    def __init__(self, cmd: list[str]) -> None:
        self.proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=REPO
        )
        assert self.proc.stdout is not None
        self.lines = LineReader(self.proc.stdout)

    def line(self, timeout: float = 30.0) -> str:
        text = self.lines.line(timeout)
        if text is None:
            raise RuntimeError(f"child exited with {self.proc.wait(5)}")
        return text.strip()

    def stop(self) -> None:
        stop_process(self.proc, signal.SIGKILL)


@contextlib.contextmanager
def topology(tmp: Path, timeout_s: float) -> Iterator[tuple[Setup, Daemon]]:
    """The daemon (calibrated, fast simulator) and where the Riders reach it from."""
    config = write_fast_config(tmp)
    config.write_text(config.read_text().replace("timeout_s = 1.0", f"timeout_s = {timeout_s}"))
    data = tmp / "data-m1"
    data.mkdir()
    (data / CALIBRATION_FILE).write_bytes(calibration_file(config.read_text()))
    with contextlib.ExitStack() as stack:
        try:
            pair: NsPair | None = stack.enter_context(veth_pair("rl"))
        except NetnsUnavailable:
            pair = None
        port = free_port()
        if pair is None:
            daemon = start_daemon(tmp, "m1", extra=["--config", str(config)], port=port)
            setup = Setup(daemon.endpoint, None, None, None)
        else:
            daemon = start_daemon(
                tmp,
                "m1",
                extra=["--config", str(config)],
                port=port,
                netns=pair.a,
                listen_host=pair.addr_a,
                wait=False,
            )
            setup = Setup(daemon.endpoint, pair.b, pair.a, pair)
        try:
            yield setup, daemon
        finally:
            daemon.stop()


def rider(setup: Setup, action: str) -> Proc:
    return Proc(
        setup.wrap(setup.rider_ns, [sys.executable, "-c", RIDER_CHILD, setup.endpoint, action])
    )


def detection(setup: Setup, trials: int) -> dict[str, list[float]]:
    """Seconds from each failure to the PAUSED cycle, per failure kind."""
    cmd = [sys.executable, "-c", OBSERVER_CHILD, setup.endpoint]
    observer = Proc(setup.wrap(setup.machine_ns, cmd))
    found: dict[str, list[float]] = {k: [] for k in KINDS if k != "veth down" or setup.pair}
    try:
        observer.line(90.0)  # homed, IDLE
        action = "start"
        for i in range(trials * len(found)):
            kind = list(found)[i % len(found)]
            child = rider(setup, action)
            try:
                child.line(30.0)  # moving
                action = "resume"
                while json.loads(observer.line())["state"] != "RUNNING":
                    pass
                time.sleep(0.2 + 0.1 * (i % 5) / 5)  # a random-ish phase against the heartbeat
                failed_at = time.time()
                if kind == "SIGKILL":
                    child.proc.send_signal(signal.SIGKILL)
                elif kind == "SIGSTOP":
                    child.proc.send_signal(signal.SIGSTOP)
                else:
                    assert setup.pair is not None
                    setup.pair.link(setup.pair.b, False)
                while (state := json.loads(observer.line()))["state"] != "PAUSED":
                    pass
                found[kind].append(state["time"] - failed_at)
            finally:
                child.stop()
                if kind == "veth down" and setup.pair is not None:
                    setup.pair.link(setup.pair.b, True)
    finally:
        observer.stop()
    return found


def cost(
    daemon: Daemon, phase_s: float, rounds: int
) -> dict[str, list[tuple[float, float, float]]]:
    """(CPU %, jitter p99 s, jitter max s) per phase, for 0 and 3 supervising Riders."""
    out: dict[str, list[tuple[float, float, float]]] = {"no Rider": [], "3 supervising Riders": []}
    setup = Setup(daemon.endpoint, None, None, None)
    meter = CpuMeter(daemon.proc.pid, family=True)
    with daemon.rider(supervise=False) as r:
        for _ in range(rounds):
            for label, rows in out.items():
                riders = [rider(setup, "idle") for _ in range(3 if label != "no Rider" else 0)]
                try:
                    for child in riders:
                        child.line(30.0)
                    r.diag(reset=True)
                    meter.start()
                    time.sleep(phase_s)
                    cpu = meter.percent()
                    d = r.diag()
                    rows.append((cpu, d.jitter.p99, d.jitter.max))
                finally:
                    for child in riders:
                        child.stop()
    return out


def run(opts: Options) -> Section:
    trials = opts.pick(3, 20)
    phase_s = opts.pick(2.0, 10.0)
    rounds = opts.pick(1, 2)
    section = Section("rider_loss", "Rider loss: the deadman heartbeat")
    # The project default for the deadman; the quick smoke run keeps the test config's 1 s, as
    # it runs beside every other benchmark and a starved Rider would pause its own ride.
    timeout_s = opts.pick(1.0, TIMEOUT_S)
    with tempfile.TemporaryDirectory(prefix="bench-rl-") as tmp_name:
        tmp = Path(tmp_name)
        with topology(tmp, timeout_s) as (setup, daemon):
            if setup.pair is not None:
                # The daemon starts in its namespace: wait for it from there.
                observer = Proc(
                    setup.wrap(setup.machine_ns, [sys.executable, "-c", WAIT_UP, setup.endpoint])
                )
                observer.line(60.0)
                observer.stop()
            found = detection(setup, trials)
    table = Table(
        f"Failure → PAUSED (relays off), {trials} trials per kind; Rider on Zenoh's default"
        f" 10 s lease, rider_loss.timeout_s {timeout_s} s, loop {PERIOD_S * 1e3:g} ms",
        ["failure", "n", "p50", "p99", "max", "bound (timeout + 2 cycles)"],
    )
    bound = timeout_s + 2 * PERIOD_S
    worst = 0.0
    for kind, values in found.items():
        d = Dist.of(values)
        worst = max(worst, d.max) if kind != "SIGKILL" else worst
        table.add(kind, len(values), ms(d.p50, 0), ms(d.p99, 0), ms(d.max, 0), ms(bound, 0))
    if "veth down" not in found:
        table.note = "veth down skipped: network namespaces need root"
    section.tables.append(table)
    section.targets.append(Target.at_most("SIGSTOP / veth down → PAUSED (max)", worst, bound, ms))
    with bench_daemon(PERIOD_S, calibrated=True) as daemon:
        costs = cost(daemon, phase_s, rounds)
    ctable = Table(
        f"Daemon idle at {PERIOD_S * 1e3:g} ms, {rounds}×{phase_s:g} s per case, interleaved",
        ["case", "CPU % of a core", "jitter p99", "jitter max"],
    )
    mean = {}
    for label, rows in costs.items():
        cpu = sum(r[0] for r in rows) / len(rows)
        mean[label] = cpu
        ctable.add(
            label, f"{cpu:.1f}", ms(max(r[1] for r in rows), 2), ms(max(r[2] for r in rows), 2)
        )
    section.tables.append(ctable)
    extra = mean["3 supervising Riders"] - mean["no Rider"]
    section.targets.append(
        Target.at_most(
            "CPU added by 3 heartbeats (% of a core)", extra, 2.0, lambda v: f"{v:.1f} %"
        )
    )
    section.notes.append(
        "Detection is the PAUSED status's own time stamp minus the failure's wall time (one"
        " host clock). SIGKILL closes the TCP link, so the Rider's liveliness token goes at"
        " once and the machine pauses in a cycle or two; SIGSTOP and a cut link leave the token"
        " alive for the Rider's whole Zenoh lease (10 s here): only the heartbeat catches them."
    )
    return section


WAIT_UP = """
import sys
from ride_machine.rider.client import Rider
with Rider("m1", connect=[sys.argv[1]], supervise=False, timeout=5.0) as r:
    for _ in range(100):
        try:
            r.status(); break
        except Exception:
            import time; time.sleep(0.2)
    print("up", flush=True)
"""


def main(argv: Sequence[str] | None = None) -> int:
    return main_for("bench.rider_loss", __doc__ or "", run, list(argv) if argv else None)


if __name__ == "__main__":
    sys.exit(main())
