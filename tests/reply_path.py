"""The files a command crosses from `rider home` to the machine's reply (issue 54).

`python -m tests.reply_path` starts a daemon on the simulator in this process, calibrates it,
then runs `rider home` (the CLI's `main`, in a thread of this process) with every Python thread
profiled, the Zenoh threads included (their callbacks are wrapped as the daemon declares them).
It prints three measures (`--json`: one JSON object, which tests/test_reply_path.py reads):

- the files the command reaches: a frame is on its path when the command travels in its
  arguments (the CLI's parsed arguments, the zenoh query or reply, the `CommandRequest`, the
  `Command`, the `Reply`), until the Rider holds the decoded reply;
- the main line: the files on the stacks at the command's hand-offs (the query sent, each
  frame of the state machine's folder that carries it, the reply sent);
- the crossings: calls between statemachine/machine.py and the other files of its folder made
  for the command (beneath machine.py's frames that carry it); those into handlers.py counted.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from types import FrameType
from typing import Any

import zenoh

from ride_machine.schema.commands import Command, CommandRequest, Reply
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.supervision.assembly import DaemonOptions
from ride_machine.service.supervision.daemon import Daemon
from tests.procs import free_port, write_zenoh_config

REPO = Path(__file__).resolve().parent.parent
PRODUCT = tuple(str(REPO / top) + "/" for top in ("schema", "common", "hal", "service", "rider"))
MACHINE_FILE = "service/core/statemachine/machine.py"
FOLDER = str(REPO / MACHINE_FILE).rsplit("/", 1)[0] + "/"
CARRIERS = (argparse.Namespace, zenoh.Query, zenoh.Reply, CommandRequest, Command, Reply)
"""What a command is while it travels: what a frame must hold in its arguments to be on the path."""


class PathTracer:
    """A profile function that keeps, while `on`, each product frame that carries the command.

    The path ends where the Rider holds the machine's reply: once a zenoh reply has reached
    the Rider's thread, the first of its frames that gets the decoded `Reply` (to print it)
    ends the trace."""

    def __init__(self) -> None:
        self.on = False
        self.rider_thread: int | None = None
        self.hops: list[tuple[str, str]] = []  # (file, function), in the order reached
        self.line: list[str] = []  # the files on the stacks at the command's hand-offs
        self.crossings: list[str] = []  # "machine.py:handle -> handlers.py:home", ...
        self._handling: set[FrameType] = set()  # machine.py's frames that carry the command
        self._answered = False
        self._lock = threading.Lock()

    def __call__(self, frame: FrameType, event: str, arg: object) -> None:
        if not self.on:
            return
        if event == "c_call":
            self._zenoh_call(frame, arg)
        elif event == "call" and frame.f_code.co_filename.startswith(PRODUCT):
            if frame.f_code.co_filename.startswith(FOLDER):
                self._crossing(frame)
            self._hop(frame)

    def _zenoh_call(self, frame: FrameType, function: object) -> None:
        """The query goes out, or the reply: a hand-off."""
        owner = getattr(function, "__self__", None)
        sends = getattr(function, "__name__", "") in ("get", "reply")
        if sends and isinstance(owner, zenoh.Session | zenoh.Query):
            self._stack(frame)

    def _hop(self, frame: FrameType) -> None:
        """`frame` is on the path if the command travels in its arguments."""
        code = frame.f_code
        count = code.co_argcount + code.co_kwonlyargcount
        names = code.co_varnames[: count + bool(code.co_flags & 0x04) + bool(code.co_flags & 0x08)]
        carried = {type(v) for v in _carried(frame.f_locals.get(name) for name in names)}
        if not carried:
            return
        if threading.get_ident() == self.rider_thread:
            if zenoh.Reply in carried:
                self._answered = True
            elif self._answered and carried <= {Reply}:
                self.on = False  # the Rider holds the reply: what follows presents it
                return
        path = str(Path(code.co_filename).relative_to(REPO))
        with self._lock:
            self.hops.append((path, code.co_name))
        if code.co_filename.startswith(FOLDER):
            self._stack(frame)  # the state machine decides
            if code.co_filename.endswith(MACHINE_FILE):
                self._handling.add(frame)

    def _crossing(self, frame: FrameType) -> None:
        """A call between machine.py and another file of its folder, made for the command
        (under one of machine.py's frames that carry it), is a crossing."""
        caller = frame.f_back
        if caller is None or not caller.f_code.co_filename.startswith(FOLDER):
            return
        ends = (caller.f_code.co_filename, frame.f_code.co_filename)
        if ends[0] == ends[1] or sum(end.endswith(MACHINE_FILE) for end in ends) != 1:
            return
        above: FrameType | None = caller
        while above is not None and above not in self._handling:
            above = above.f_back
        if above is not None:
            names = (
                f"{Path(f.f_code.co_filename).name}:{f.f_code.co_name}" for f in (caller, frame)
            )
            with self._lock:
                self.crossings.append(" -> ".join(names))

    def _stack(self, frame: FrameType | None) -> None:
        """The product files on `frame`'s stack: where the command rides at a hand-off."""
        files = []
        while frame is not None:
            if frame.f_code.co_filename.startswith(PRODUCT):
                files.append(str(Path(frame.f_code.co_filename).relative_to(REPO)))
            frame = frame.f_back
        with self._lock:
            self.line.extend(reversed(files))

    def files(self) -> list[str]:
        return list(dict.fromkeys(path for path, _ in self.hops))


def _carried(values: Iterable[object]) -> Iterator[object]:
    """The carriers among `values`, and in a list or tuple among them (a batch of replies)."""
    for value in values:
        if isinstance(value, CARRIERS):
            yield value
        elif isinstance(value, list | tuple):
            yield from (v for v in value[:8] if isinstance(v, CARRIERS))


def _profiled(tracer: PathTracer, handler: Callable[..., Any]) -> Callable[..., Any]:
    """`handler` run with the tracer on its (Zenoh) thread, which Python did not start."""

    def run(*args: Any) -> Any:
        sys.setprofile(tracer)
        try:
            return handler(*args)
        finally:
            sys.setprofile(None)

    return run


def _wrap_declarations(tracer: PathTracer) -> None:
    """Every queryable and subscriber the daemon declares calls back under the tracer."""
    for name in ("declare_queryable", "declare_subscriber"):
        original = getattr(zenoh.Session, name)

        def declare(
            self: zenoh.Session, key: Any, handler: Any = None, *a: Any, _o=original, **kw: Any
        ) -> Any:
            if callable(handler):
                handler = _profiled(tracer, handler)
            return _o(self, key, handler, *a, **kw)

        setattr(zenoh.Session, name, declare)


def _daemon(data: Path, *, relaxed: bool) -> tuple[Daemon, str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    loop: dict[str, Any] = {"gc_freeze": False}
    if relaxed:  # every call of every thread goes through the profile function
        loop |= {"period_s": 0.05, "watchdog_min_s": 2.0}
    config = MachineConfig().with_overrides(loop=loop)
    config = config.model_copy(update={"data_dir": str(data / "data")})
    options = DaemonOptions(zenoh_config=write_zenoh_config(data), listen=[endpoint])
    return Daemon(config, options), endpoint


def _serve(daemon: Daemon, endpoint: str, commands: Callable[[list[str]], None]) -> None:
    """Run `daemon` on this (the main) thread while `commands` gets the CLI's base arguments
    on another, once the loop runs; the daemon stops when they are done."""

    def drive() -> None:
        try:
            for _ in range(1000):  # bounded: 10 s until the loop runs
                if daemon.runner is not None and daemon.runner.pulse.count >= 3:
                    break
                threading.Event().wait(0.01)
            commands(["--connect", endpoint, "--machine", daemon.config.machine.id])
        finally:
            signal.raise_signal(signal.SIGTERM)

    thread = threading.Thread(target=drive, daemon=True)
    thread.start()
    daemon.run()
    thread.join(timeout=30)


def trace_home() -> dict[str, Any]:
    """Calibrate a daemon (untraced, at its normal period), then run it again from the same
    data folder (calibrated, relaxed, every thread profiled) and trace one `rider home`."""
    from ride_machine.rider.cli import main

    tracer = PathTracer()
    out: dict[str, Any] = {}

    def calibrate(base: list[str]) -> None:
        for axis in ("tilt", "rotate"):
            out[f"calibrate {axis}"] = main([*base, "calibrate", axis, "--wait"])

    def home(base: list[str]) -> None:
        tracer.rider_thread = threading.get_ident()
        tracer.on = True
        out["home"] = main([*base, "home"])
        tracer.on = False

    with tempfile.TemporaryDirectory() as tmp:
        _serve(*_daemon(Path(tmp), relaxed=False), calibrate)
        _wrap_declarations(tracer)
        threading.setprofile(tracer)
        _serve(*_daemon(Path(tmp), relaxed=True), home)
        threading.setprofile(None)  # type: ignore[arg-type]
    files = tracer.files()
    line = list(dict.fromkeys(tracer.line))
    return {
        "codes": out,
        "files": files,
        "file_count": len(files),
        "line": line,
        "line_count": len(line),
        "hops": tracer.hops,
        "crossings": tracer.crossings,
        "handler_crossings": sum("handlers.py:" in c for c in tracer.crossings),
    }


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.reply_path", description=__doc__)
    parser.add_argument("--json", action="store_true", help="one JSON object on stdout")
    found = trace_home()
    if parser.parse_args().json:
        print(json.dumps(found))
        return 0
    print(f"rider home -> reply: exits {found['codes']}, {found['file_count']} files")
    for number, path in enumerate(found["files"], 1):
        print(f"{number:3} {path}")
    print(f"of them on the stacks at its hand-offs (the main line): {found['line_count']}")
    for path in found["line"]:
        print(f"    {path}")
    print(f"machine.py <-> handlers.py: {found['handler_crossings']} crossings, of these calls")
    print("between machine.py and the other files of its folder, made for the command:")
    for crossing in found["crossings"]:
        print(f"    {crossing}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
