"""What this host grants the scan loop: whether `loop.rt_priority` can take effect here.

A scan thread under `SCHED_FIFO` keeps its period beside CPU-bound neighbours; the kernel gives
that class to a thread whose process has `CAP_SYS_NICE` (root, or a container with `cap_add:
[SYS_NICE]`) or an `RLIMIT_RTPRIO` at least the priority (`ulimits: rtprio`), and a cgroup may
still refuse it (no real-time budget). So the check asks the kernel: a short-lived thread of
this process tries the priority and ends (the class dies with the thread). `machine validate`
reports the answer; `machine run` and `supervise` print it with the host's other findings
before they start, and the start line says what was applied (`tuning=…SCHED_FIFO=n`).
"""

from __future__ import annotations

import os
import threading

from ride_machine.schema.findings import Finding

from .model import MachineConfig
from .report import Category, warning

PATH = "/loop/rt_priority"


def realtime_findings(config: MachineConfig) -> list[Finding]:
    """A warning when `loop.rt_priority` is set and this process may not use it."""
    priority = config.loop.rt_priority
    if priority is None:
        return []
    refused = fifo_refused(priority)
    if refused is None:
        return []
    return [
        warning(
            Category.REALTIME,
            PATH,
            f"SCHED_FIFO priority {priority} is not granted here ({refused}): the scan thread"
            " runs as an ordinary thread, and a busy host can make it late. Grant it:"
            " CAP_SYS_NICE (compose: cap_add: [SYS_NICE]) or an rtprio limit of at least"
            f" {priority} (compose: ulimits: rtprio: {priority}; systemd: LimitRTPRIO=)",
            priority=priority,
        )
    ]


def fifo_refused(priority: int) -> str | None:
    """None when a thread of this process may run `SCHED_FIFO` at `priority`; else why not."""
    if not hasattr(os, "sched_setscheduler"):
        return "this system has no SCHED_FIFO"
    answer: list[str | None] = []

    def attempt() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            answer.append(None)
        except OSError as exc:
            answer.append(exc.strerror or str(exc))

    probe = threading.Thread(target=attempt, name="rt-probe", daemon=True)
    probe.start()
    probe.join(5.0)
    return answer[0] if answer else "the probe did not answer"
