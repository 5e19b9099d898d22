"""The daemon's own `RealtimeRunner` with a scan that does nothing: the floor for loop timing.

Same sleep strategy, same statistics code, same tuning options; the difference to the daemon
is the scan's work and the Zenoh threads.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from typing import Any, cast

from ride_machine.service.core.scan.inbox import Inbox
from ride_machine.service.core.scan.loop import ScanLoop
from ride_machine.service.core.scan.runner import RealtimeRunner
from ride_machine.service.core.scan.timing import CycleStats
from ride_machine.service.core.scan.tuning import (
    SCHED_SLICE_NS,
    TIMER_SLACK_NS,
    slice_process,
    tune_thread,
)


class EmptyScan:
    """What `RealtimeRunner` needs of a `ScanLoop`, with no work in it."""

    def __init__(self) -> None:
        self.inbox: Inbox[ScanLoop] = Inbox()
        self.commands_handled = 0
        self.lock = threading.Lock()
        self.guard = None  # no watchdog latch: nothing to stamp in a beat record

    def step(self, now: float) -> None:
        pass

    def service_inbox(self, now: float) -> int:
        return len(self.inbox.take(64))

    def go_safe(self) -> None:
        pass


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--period", type=float, required=True, help="seconds")
    parser.add_argument("--duration", type=float, required=True, help="seconds to run")
    parser.add_argument("--spin", type=float, default=0.0, help="busy-wait tail (seconds)")
    parser.add_argument("--no-gc-freeze", action="store_true")
    parser.add_argument("--cpu", type=int)
    parser.add_argument("--rt-priority", type=int)
    parser.add_argument(
        "--kernel-timer-slack", action="store_true", help="keep the kernel's timer slack"
    )
    parser.add_argument(
        "--kernel-slice", action="store_true", help="keep the kernel's time slice (slice_s = 0)"
    )
    args = parser.parse_args(argv)
    stats = CycleStats(args.period, 100_000, time.time())
    runner = RealtimeRunner(cast(ScanLoop, EmptyScan()), args.period, stats, spin_s=args.spin)
    slack = None if args.kernel_timer_slack else TIMER_SLACK_NS
    applied = tune_thread(not args.no_gc_freeze, args.cpu, args.rt_priority, slack)
    if not args.kernel_slice and (sliced := slice_process(SCHED_SLICE_NS)):
        applied.append(sliced)  # as the daemon's `loop.slice_s` does
    timer = threading.Timer(args.duration, runner.stop)
    timer.daemon = True
    timer.start()
    print("ready", flush=True)
    runner.run()
    diag: dict[str, Any] = stats.diag(time.time()).model_dump(mode="json")
    diag["tuning"] = applied
    print("result " + json.dumps(diag), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
