"""The container healthcheck's cost: round two's check (`rider … status`, a fresh Python and Zenoh
session each time) against the heartbeat file's (`find FILE -mmin -0.1 | grep -q .`), both run
as the engine runs them, against one daemon started with `MACHINE_HEARTBEAT_FILE`.

Per check: CPU seconds (user + system of the check's process tree, from `wait4`) and peak RSS
(the largest process of the tree); and the daemon's own CPU while a check runs every second
(a session that connects costs the daemon too), against a stretch with no check at all.
"""

from __future__ import annotations

import functools
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from bench.common import NAN, CpuMeter, Options, Section, Table, Target, main_for
from ride_machine.service.adapters.heartbeat import HEARTBEAT_FILE_ENV
from tests.procs import rider_cmd, start_daemon

NEW_CHECK = "find {file} -mmin -0.1 | grep -q ."
"""compose.yaml's machine healthcheck, run by the engine as `/bin/sh -c`."""
COMPOSE_INTERVAL_S = 5.0
"""compose.yaml's healthcheck interval: the check's own CPU counts in the container's."""
GOAL_SHARE = 0.1
"""Issue 41: 'a fraction of today's CPU and memory': at most a tenth of each."""


GNU_TIME = "/usr/bin/time"
"""Peak RSS is measured by GNU time: Linux carries a process's RSS high-water mark over fork
and exec, so `wait4` on a check started from this (large) Python process reports this
process's size, not the check's."""


def one(argv: list[str]) -> tuple[float, float, int]:
    """(CPU seconds, peak RSS bytes, exit code) of one check and its children: CPU from
    `wait4` (GNU time's own share is negligible), peak RSS from GNU time's `%M` (NaN without
    GNU time)."""
    timed = Path(GNU_TIME).exists()
    prefix = [GNU_TIME, "-f", "maxrss_kib=%M"] if timed else []
    proc = subprocess.Popen(
        [*prefix, *argv], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    assert proc.stderr is not None
    err = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    rss = float(err.rsplit("maxrss_kib=", 1)[1].split()[0]) * 1024 if timed else NAN
    return usage.ru_utime + usage.ru_stime, rss, proc.returncode


def checks(endpoint: str, heartbeat: Path) -> dict[str, list[str]]:
    old = rider_cmd("--connect", endpoint, "--timeout", "2", "--machine", "m1", "status")
    return {
        "round two: rider status (Zenoh session)": old,
        "heartbeat file: find | grep": ["/bin/sh", "-c", NEW_CHECK.format(file=heartbeat)],
    }


def daemon_share(pid: int, seconds: float, check: Callable[[], object] | None) -> float:
    """The daemon's CPU % of one core over `seconds`, with `check` run once a second."""
    meter = CpuMeter(pid, family=True)
    meter.start()
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        tick = time.monotonic()
        if check is not None:
            check()
        time.sleep(max(0.0, min(left, 1.0 - (time.monotonic() - tick))))
    return meter.percent()


def run(opts: Options) -> Section:
    section = Section("healthcheck", "11. The container healthcheck's cost")
    rounds = opts.pick(3, 30, 100)
    window_s = opts.pick(3.0, 20.0, 60.0)
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        heartbeat = tmp / "machine.heartbeat"
        daemon = start_daemon(tmp, env={HEARTBEAT_FILE_ENV: str(heartbeat)})
        try:
            while not heartbeat.exists():  # the first touch comes about a second in
                time.sleep(0.05)
            kinds = checks(daemon.endpoint, heartbeat)
            samples: dict[str, list[tuple[float, float, int]]] = {k: [] for k in kinds}
            for r in range(rounds):
                for name in list(kinds) if r % 2 == 0 else list(kinds)[::-1]:
                    samples[name].append(one(kinds[name]))
            shares = {"no check": daemon_share(daemon.proc.pid, window_s, None)}
            for name, argv in kinds.items():
                shares[name] = daemon_share(daemon.proc.pid, window_s, functools.partial(one, argv))
        finally:
            daemon.stop()
    table = Table(
        "Per check (median over the rounds), and the daemon while a check runs every second",
        ["check", "exit 0", "CPU per check", "a core at 1 check / 5 s", "peak RSS",
         "daemon CPU (1 check/s)"],
    )  # fmt: skip
    table.add("no check", "—", "—", "—", "—", f"{shares['no check']:.1f} %")
    medians = {}
    for name, rows in samples.items():
        cpu = statistics.median(r[0] for r in rows)
        rss = statistics.median(r[1] for r in rows)
        medians[name] = (cpu, rss)
        ok = sum(r[2] == 0 for r in rows)
        table.add(
            name, f"{ok}/{len(rows)}", f"{cpu * 1e3:.1f} ms",
            f"{100 * cpu / COMPOSE_INTERVAL_S:.2f} %", _mib(rss),
            f"{shares[name]:.1f} %",
        )  # fmt: skip
    section.tables.append(table)
    (old_cpu, old_rss), (new_cpu, new_rss) = medians.values()
    section.targets += [
        Target.at_most("CPU per check, new / old", new_cpu / old_cpu, GOAL_SHARE, _pct),
        Target.at_most("peak RSS per check, new / old", new_rss / old_rss, GOAL_SHARE, _pct),
    ]
    section.notes.append(
        f"{rounds} checks of each kind, alternating; daemon CPU over {window_s:g} s per row "
        "(its history process included). The old check ran on this host's Python with the "
        "package installed, as in the image; the new one is the image's `/bin/sh -c` string."
    )
    return section


def _mib(n: float) -> str:
    return "— (no GNU time)" if math.isnan(n) else f"{n / 2**20:.1f} MiB"


def _pct(share: float) -> str:
    return f"{share * 100:.1f} %"


if __name__ == "__main__":
    sys.exit(main_for("bench.healthcheck", __doc__ or "", run))
