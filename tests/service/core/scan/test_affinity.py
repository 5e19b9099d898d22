"""`loop.cpus`: the whole daemon, every thread, on the CPUs given (read from outside, in /proc)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from pydantic import ValidationError

from ride_machine.service.config.model import LoopSection
from tests.probes import call_among_threads, thread_cpus
from tests.procs import running_daemon

several_cpus = pytest.mark.skipif(
    len(os.sched_getaffinity(0)) < 2, reason="pinning to one CPU changes nothing on a single CPU"
)


def thread_cpus_of(cpus: str) -> tuple[str, str]:
    """A child that pins itself to `cpus` with threads running: (applied, each thread's CPUs)."""
    return call_among_threads(
        "from ride_machine.service.core.scan.tuning import pin_process\n"
        "from tests.probes import thread_cpus",
        "pin_process([int(c) for c in sys.argv[1].split(',')])",
        "sorted(set(map(tuple, thread_cpus(os.getpid()).values())))",
        cpus,
    )


@several_cpus
def test_every_thread_is_pinned_those_before_and_those_after() -> None:
    cpu = min(os.sched_getaffinity(0))
    applied, threads = thread_cpus_of(str(cpu))
    assert applied == f"cpus={cpu}"
    assert threads == f"[({cpu},)]"  # all four threads: main, two before, one after


def test_cpus_that_do_not_exist_are_refused_and_nothing_changes() -> None:
    applied, threads = thread_cpus_of("4000")
    assert applied == "None"
    assert threads == str([tuple(sorted(os.sched_getaffinity(0)))])


def test_the_cpu_list_is_checked() -> None:
    assert LoopSection(cpus=[1, 0]).cpus == [1, 0]
    for bad in ([], [-1]):
        with pytest.raises(ValidationError):
            LoopSection(cpus=bad)


@several_cpus
@pytest.mark.integration
def test_a_daemon_runs_all_its_threads_on_the_cpus_configured(tmp_path: Path) -> None:
    """Zenoh's threads, the callbacks', the writers' and the scan's: the start line says so."""
    cpu = max(os.sched_getaffinity(0))
    config = tmp_path / "machine.toml"
    config.write_text(f"[loop]\ncpus = [{cpu}]\n")
    with running_daemon(tmp_path, extra=["--config", str(config)]) as daemon:
        with daemon.rider(timeout=5.0) as rider:
            assert rider.check_home() is not None  # a command ran on a callback thread
        threads = thread_cpus(daemon.proc.pid)
        assert len(threads) > 5
        assert set(threads.values()) == {(cpu,)}
        assert daemon.has_logged(f"cpus={cpu}")
