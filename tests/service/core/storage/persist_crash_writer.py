"""The crash test's child: forks writers that persist parameters and calibration in a tight loop.

It imports everything once, then serves the test over stdin/stdout, one line each way:
`go <first>` forks a writer that prints `pid <pid>`, then writes rounds first, first+1, ...
and prints `w <i>` after round i is complete; the test SIGKILLs the writer, and this process
prints `reaped <pid>` once the writer is dead. Forking from here keeps each kill cheap (no
interpreter start-up per kill).
"""

from __future__ import annotations

import os
import sys
import traceback
from collections.abc import Callable
from pathlib import Path

from ride_machine.schema.params import ParamSet
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.motion.devices import Calibration, RotateCalibration, TiltCalibration
from ride_machine.service.core.storage.params import ParamRegistry
from ride_machine.service.core.storage.persist import CalibrationStore, ParamStore

FIRST, SECOND = "tilt.tolerance_deg", "bus.heartbeat_s"
"""Ordinary parameters: a safety setting may not be made less strict online (safety.py)."""


def first_value(i: int) -> float:
    """Round i's value of the first parameter (inside its range whatever i is)."""
    return 0.5 + (i % 900) * 0.01


def second_value(i: int) -> float:
    return 1.0 + (i % 500) * 0.1


def calibration(i: int) -> Calibration:
    return Calibration(
        tilt=TiltCalibration(offset_counts=float(i), gain_counts_per_deg=40.0),
        rotate=RotateCalibration(revolution_s=4.0, home_arc_deg=10.0),
    )


def _say(text: str) -> None:
    # os.write, not print: no buffer that a fork could copy or a kill could lose.
    os.write(1, (text + "\n").encode())


def write_forever(data_dir: Path, first: int, parent: int) -> None:
    """One round: two persisted parameters, then the calibration, each an atomic write."""
    registry = ParamRegistry(MachineConfig(), ParamStore(data_dir))
    store = CalibrationStore(data_dir, clock=lambda: 0.0)
    _say(f"pid {os.getpid()}")
    i = first
    while os.getppid() == parent:  # never outlive the server that forked us
        for name, value in ((FIRST, first_value(i)), (SECOND, second_value(i))):
            req = ParamSet(transaction_id=f"t{i}", value=value, persist=True)
            registry.set(name, req, moving=False, now=float(i))
        store.save(calibration(i))
        _say(f"w {i}")
        i += 1


Writer = Callable[[Path, int, int], None]
"""What a forked child runs: (data_dir, first round, parent pid); it only ends by a kill."""


def serve(data_dir: Path, writer: Writer | None = None) -> None:
    """Fork a `writer` (default `write_forever`) per `go <first>` line; report `reaped <pid>`."""
    writer = writer or write_forever
    _say("ready")
    for line in sys.stdin:
        word, _, arg = line.strip().partition(" ")
        if word != "go":
            return
        parent = os.getpid()
        pid = os.fork()
        if pid == 0:
            try:
                writer(data_dir, int(arg), parent)
            except BaseException:
                traceback.print_exc()
                raise
            finally:
                os._exit(1)  # the writer only ends by a kill: anything else is a failure
        os.waitpid(pid, 0)
        _say(f"reaped {pid}")


if __name__ == "__main__":
    serve(Path(sys.argv[1]))
