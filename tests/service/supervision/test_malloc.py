"""`loop.malloc_arenas`: a daemon's glibc malloc arenas stay bounded however many threads
allocate (its RSS under Rider churn depends on it: BENCHMARKS.md section 5). Counted from
outside, in /proc."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from ride_machine.service.supervision.malloc import ARENA_ENV, MALLOC_ARENAS, TUNABLES_ENV
from tests.procs import REPO, malloc_arenas, running_daemon

glibc_only = pytest.mark.skipif(
    not sys.platform.startswith("linux") or os.confstr("CS_GNU_LIBC_VERSION") is None,
    reason="glibc's malloc arenas",
)

THREADS = 8
CHILD = """
import sys, threading
from ride_machine.service.supervision.malloc import bound_malloc_arenas
from tests.procs import malloc_arenas
applied = bound_malloc_arenas() if sys.argv[1] == "bound" else None
held = threading.Barrier({threads} + 1)
def body():
    block = bytearray(64 * 1024)  # from the thread's arena (below the mmap threshold)
    held.wait(10)
    held.wait(10)
threads = [threading.Thread(target=body) for _ in range({threads})]
for t in threads:
    t.start()
held.wait(10)  # every thread has allocated and is still alive
import os
print(applied, malloc_arenas(os.getpid()))
held.wait(10)
for t in threads:
    t.join(10)
"""


def _threads_allocate(mode: str, **env: str) -> tuple[str, int]:
    """A child whose threads each allocate: (what `bound_malloc_arenas` returned, arenas)."""
    clean = {k: v for k, v in os.environ.items() if k not in (ARENA_ENV, TUNABLES_ENV)}
    proc = subprocess.run(
        [sys.executable, "-c", CHILD.format(threads=THREADS), mode],
        cwd=REPO,
        env={**clean, **env},
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    applied, arenas = proc.stdout.split()
    return applied, int(arenas)


@glibc_only
def test_bounded_process_allocates_from_two_arenas_however_many_threads() -> None:
    applied, arenas = _threads_allocate("bound")
    assert applied == "True"
    assert arenas <= MALLOC_ARENAS
    # The same threads without the bound: one arena each (so the count above means something).
    _, unbounded = _threads_allocate("free")
    assert unbounded > MALLOC_ARENAS


@glibc_only
def test_the_environments_arena_cap_wins() -> None:
    applied, arenas = _threads_allocate("bound", **{ARENA_ENV: "4"})
    assert applied == "False"
    assert MALLOC_ARENAS < arenas <= 4
    applied, _ = _threads_allocate("bound", **{TUNABLES_ENV: "glibc.malloc.arena_max=4"})
    assert applied == "False"


@glibc_only
@pytest.mark.integration
@pytest.mark.parametrize("cap", [MALLOC_ARENAS, None])
def test_a_daemon_caps_its_arenas_when_configured_to(tmp_path: Path, cap: int | None) -> None:
    """`loop.malloc_arenas = 2`: a daemon serving Riders allocates from 2 arenas and says so in
    its start line; by default glibc's own cap holds (more arenas, nothing said)."""
    clean = {k: os.environ.pop(k) for k in (ARENA_ENV, TUNABLES_ENV) if k in os.environ}
    config = tmp_path / "machine.toml"
    config.write_text("[loop]\n" + (f"malloc_arenas = {cap}\n" if cap else ""))
    try:
        with running_daemon(tmp_path, extra=["--config", str(config)]) as daemon:
            for _ in range(3):  # Zenoh's threads and the callbacks' run for each Rider
                with daemon.rider(timeout=5.0) as rider:
                    rider.status()
            arenas = malloc_arenas(daemon.proc.pid)
            logged = daemon.has_logged(f"malloc_arenas={MALLOC_ARENAS}")
            if cap:
                assert arenas <= cap and logged
            else:
                assert arenas > MALLOC_ARENAS and not logged
    finally:
        os.environ.update(clean)
