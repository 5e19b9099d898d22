"""`loop.slice_s`: every thread of the daemon on a short time slice under the normal policy
(Linux 6.12+'s EEVDF), read from outside in /proc; the kernel's own slice when it is 0."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from pydantic import ValidationError

from bench.common import children
from ride_machine.service.config.model import LoopSection
from ride_machine.service.config.validate import validate_data
from ride_machine.service.core.scan.tuning import SCHED_SLICE_NS, sched_slice
from tests.probes import call_among_threads, thread_slices
from tests.procs import running_daemon

KERNEL_SLICE = thread_slices(os.getpid()).get(os.getpid())
"""This process's slice as the kernel gave it (the test process asks for none)."""

custom_slices = pytest.mark.skipif(
    sched_slice() is None or KERNEL_SLICE is None,
    reason="this kernel has no custom time slices for the normal policy (Linux 6.12+)",
)


def slices_of(ns: int) -> tuple[str, str]:
    """A child that asks for `ns` with threads running: (applied, each thread's slice)."""
    return call_among_threads(
        "from ride_machine.service.core.scan.tuning import slice_process\n"
        "from tests.probes import thread_slices",
        "slice_process(int(sys.argv[1]))",
        "sorted(thread_slices(os.getpid()).values())",
        str(ns),
    )


@custom_slices
def test_every_thread_gets_the_slice_those_before_and_those_after() -> None:
    applied, threads = slices_of(SCHED_SLICE_NS)
    assert applied == f"slice={SCHED_SLICE_NS}ns"
    assert threads == str([SCHED_SLICE_NS] * 4)  # main, two before, one after


@custom_slices
def test_a_slice_the_kernel_clamps_is_reported_not_applied() -> None:
    """50 µs is held as the kernel's least, 100 µs: not what was asked, so not claimed."""
    applied, threads = slices_of(50_000)
    assert applied == "None"
    assert threads == str([100_000] * 4)


def test_the_slice_is_checked_where_it_is_configured() -> None:
    assert LoopSection().slice_s == 0.0001
    assert LoopSection().slice_ns == SCHED_SLICE_NS
    assert LoopSection(slice_s=0).slice_ns is None  # the kernel's own
    with pytest.raises(ValidationError):
        LoopSection(slice_s=0.5)
    config, report = validate_data({"loop": {"slice_s": 0.00005}})
    assert config is None
    assert [(f.path, f.category, f.severity.value) for f in report.findings] == [
        ("/loop/slice_s", "out_of_range", "error")
    ]
    assert "0 keeps the kernel's own" in report.findings[0].message


@custom_slices
@pytest.mark.integration
def test_a_daemon_runs_every_thread_and_its_history_process_on_the_slice(
    tmp_path: Path,
) -> None:
    """Zenoh's threads, the callbacks', the writers', the scan's and the history process's."""
    with running_daemon(tmp_path) as daemon:
        with daemon.rider(timeout=5.0) as rider:
            assert rider.check_home() is not None  # a command ran, its events were written
        pids = [daemon.proc.pid, *children(daemon.proc.pid)]
        assert len(pids) == 2  # the daemon and its history process
        slices = [s for pid in pids for s in thread_slices(pid).values()]
        assert len(slices) > 5
        assert set(slices) == {SCHED_SLICE_NS}
        assert daemon.has_logged(f"slice={SCHED_SLICE_NS}ns")


@custom_slices
@pytest.mark.integration
def test_slice_zero_leaves_the_daemon_on_the_kernels_slice(tmp_path: Path) -> None:
    config = tmp_path / "machine.toml"
    config.write_text("[loop]\nslice_s = 0\n")
    with running_daemon(tmp_path, extra=["--config", str(config)]) as daemon:
        assert daemon.has_logged("event=started")
        assert set(thread_slices(daemon.proc.pid).values()) == {KERNEL_SLICE}
        assert "slice=" not in daemon.log()
