"""Where a frozen daemon's threads were, as the kernel saw them, for the log before it is killed.

A daemon that stops cycling or answering is killed and replaced (`children.py`), and why it
stopped goes with it. Each thread's state, what it waited in and its time on and waiting for a
CPU (`/proc/<pid>/task`) tell the usual causes apart: stopped by a signal (`T`), blocked on a
lock or the GIL (`S` in a futex, no CPU time between two looks), starved by a busy host (`R`,
its wait for a CPU growing), stuck in the kernel (`D`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

MOST_THREADS = 32
"""A daemon has about a dozen threads; more are summed up, not listed."""


@dataclass(frozen=True)
class ThreadState:
    tid: int
    name: str
    state: str
    """The kernel's one-letter state: R running or runnable, S sleeping, D in the kernel, T
    stopped, Z gone."""
    wchan: str
    """The kernel function it sleeps in ("" when running)."""
    run_ns: int
    wait_ns: int
    """Time it ran, and time it was runnable but waited for a CPU (`schedstat`)."""


def threads(pid: int, proc: Path = Path("/proc")) -> list[ThreadState]:
    """Every thread of `pid` as the kernel has it now; [] when the process is gone."""
    out: list[ThreadState] = []
    try:
        tids = sorted(int(t.name) for t in (proc / str(pid) / "task").iterdir())
    except (OSError, ValueError):
        return out
    for tid in tids:
        task = proc / str(pid) / "task" / str(tid)
        try:
            stat = (task / "stat").read_text()
            sched = (task / "schedstat").read_text().split()
            wchan = (task / "wchan").read_text().strip()
        except OSError:  # a thread that has just ended
            continue
        name = stat[stat.index("(") + 1 : stat.rindex(")")]
        state = stat[stat.rindex(")") + 2 :].split()[0]
        run_ns, wait_ns = (int(sched[0]), int(sched[1])) if len(sched) >= 2 else (0, 0)
        out.append(ThreadState(tid, name, state, "" if wchan == "0" else wchan, run_ns, wait_ns))
    return out


def describe(now: list[ThreadState], before: list[ThreadState] | None = None) -> str:
    """One line: `name:state[:wchan] ran=+ms waited=+ms` per thread, the times since `before`
    (the same threads looked at earlier) where given, else in all."""
    earlier = {t.tid: t for t in before or []}
    parts = []
    for t in now[:MOST_THREADS]:
        was = earlier.get(t.tid)
        ran = (t.run_ns - was.run_ns) if was else t.run_ns
        waited = (t.wait_ns - was.wait_ns) if was else t.wait_ns
        sign = "+" if was else ""
        where = f"{t.name}:{t.state}" + (f":{t.wchan}" if t.wchan else "")
        parts.append(f"{where} ran={sign}{ran / 1e6:.0f}ms waited={sign}{waited / 1e6:.0f}ms")
    if len(now) > MOST_THREADS:
        parts.append(f"and {len(now) - MOST_THREADS} more")
    return "; ".join(parts) or "gone"
