"""`make test-under-load`: the whole suite beside one CPU-bound process per core, as a busy CI
host runs it. The arguments go to pytest (e.g. `--order reverse`, `--order random`).

    python -m tests.under_load [PYTEST ARGS...]

The neighbours are bench/baselines/burner.py processes (pure Python, no pause), started before
the suite and stopped after it, whatever its outcome; their lifetime bounds them if this
process is killed. The exit code is pytest's.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

from tests.procs import REPO, stop_process

LIFETIME_S = 3600.0
"""A neighbour left behind by a killed run ends by itself after this."""


def main(argv: list[str]) -> int:
    cores = os.cpu_count() or 1
    burners = [
        subprocess.Popen(
            [sys.executable, "-m", "bench.baselines.burner", "--lifetime", str(LIFETIME_S)],
            cwd=REPO,
            stdout=subprocess.DEVNULL,
        )
        for _ in range(cores)
    ]
    print(f"under load: {cores} CPU-bound neighbours (pids {[b.pid for b in burners]})")
    t0 = time.monotonic()
    try:
        return subprocess.call([sys.executable, "-m", "pytest", *argv], cwd=REPO)
    finally:
        for burner in burners:
            stop_process(burner)
        load = "/".join(f"{x:.1f}" for x in os.getloadavg())
        print(f"under load: {time.monotonic() - t0:.0f} s, load average at the end {load}")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
