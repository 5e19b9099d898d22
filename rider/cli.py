"""The `rider` command: operate a machine from a terminal or a script.

Exit codes: 0 done; 1 the machine refused (its error is printed), or a motion `--wait`ed for
ended otherwise than DONE; 2 bad usage or input; 3 no reply (machine or network down); 4
several machines alive and none named; 5 more than one session answers for the machine id
(two daemons share it: DUPLICATE_ID); 6 `--wait` heard nothing from the machine for
`--link-limit` seconds (the link stayed down: a ride this Rider supervised was paused by the
machine's deadman; see `rider status` once the link is back).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import sys
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

from .errors import CommandRefused, DuplicateMachine, RiderError
from .exits import (
    EXIT_AMBIGUOUS,
    EXIT_DUPLICATE,
    EXIT_LINK_LOST,
    EXIT_NO_REPLY,
    EXIT_OK,
    EXIT_REFUSED,
    EXIT_USAGE,
    EXITS,
    UsageError,
)
from .subcommands import parsers
from .text import printable

N = TypeVar("N", int, float)

__all__ = [
    "EXIT_AMBIGUOUS",
    "EXIT_DUPLICATE",
    "EXIT_LINK_LOST",
    "EXIT_NO_REPLY",
    "EXIT_OK",
    "EXIT_REFUSED",
    "EXIT_USAGE",
    "UsageError",
    "build_parser",
    "main",
]

SUBCOMMANDS = (
    parsers.add_status,
    parsers.add_watch,
    parsers.add_motions,
    parsers.add_calibration,
    parsers.add_done,
    parsers.add_check,
    parsers.add_io,
    parsers.add_axes,
    parsers.add_diag,
    parsers.add_params,
    parsers.add_validate,
    parsers.add_machines,
    parsers.add_sim,
    parsers.add_events,
)
"""The sub-commands run on a Rider, in the order `rider --help` lists them; each parser carries
its handler (`args.func`), loaded when it runs: this module and the parsers import neither Zenoh
nor a wire model, so `rider --help` and bad usage answer at once
(tests/rider/test_cli_imports.py)."""

OWN_OPTIONS = ("fastdata", "ui", "gateway")
"""Sub-commands that parse their own options (rider/fastdata.py, rider/ui/app.py,
rider/gateway/cli.py)."""

ZENOH_THREADS_MAX = 64
"""As the daemon's `bus.zenoh_threads`."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="rider", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    _global_options(p)
    sub = p.add_subparsers(dest="cmd", required=True)
    for add in SUBCOMMANDS:
        add(sub)
    sub.add_parser("fastdata", help="read the FastData UDP axis stream", add_help=False)
    sub.add_parser("ui", help="serve the operator web UI", add_help=False)
    sub.add_parser("gateway", help="OPC UA and Prometheus for the plant", add_help=False)
    return p


def _global_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--connect",
        action="append",
        default=[],
        help="Zenoh endpoint of the machine (default tcp/127.0.0.1:7447 or $RIDER_CONNECT)",
    )
    p.add_argument("--zenoh-config", type=Path, help="zenoh.json5 (shared with the daemon)")
    p.add_argument(
        "--machine",
        "-m",
        type=_machine_id,
        default=None,
        help="machine id (default: the only machine alive)",
    )
    p.add_argument("--prefix", default="machine", help="key prefix (default: machine)")
    p.add_argument("--timeout", type=_positive_s, default=2.0, help="reply timeout in seconds")
    p.add_argument(
        "--zenoh-threads",
        type=_zenoh_threads,
        default=1,
        help="Zenoh's worker threads in this process (default 1, as the daemon; 0: Zenoh's own"
        " six; $ZENOH_RUNTIME wins)",
    )
    p.add_argument("--json", action="store_true", help="print JSON instead of tables")


def _machine_id(text: str) -> str:
    """One key chunk (`*` allowed: reads across machines); checked before any Zenoh call."""
    if not text or "/" in text:
        raise argparse.ArgumentTypeError(f"{text!r} is not a machine id (one key part, no '/')")
    return text


def _checked(read: Callable[[str], N], ok: Callable[[N], bool], what: str) -> Callable[[str], N]:
    """An option's type: `read(text)` where `ok`, else "'text' is not `what`" (bad usage)."""

    def value_of(text: str) -> N:
        try:
            value = read(text)
        except ValueError:
            value = None
        if value is None or not ok(value):
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}")
        return value

    return value_of


_positive_s = _checked(float, lambda s: math.isfinite(s) and s > 0, "a positive number of seconds")
_zenoh_threads = _checked(
    int,
    lambda n: 0 <= n <= ZENOH_THREADS_MAX,
    f"a thread count from 0 (Zenoh's own layout) to {ZENOH_THREADS_MAX}",
)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args, rest = parser.parse_known_args(argv)
    if args.cmd not in OWN_OPTIONS and rest:
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    if args.cmd == "fastdata" and (code := _fastdata(args, rest)) is not None:
        return code
    from .link import env_connect  # Zenoh: only for a command that runs

    connect = args.connect or env_connect()
    if args.cmd == "gateway":
        from ride_machine.rider.gateway.cli import main as gateway_main

        return gateway_main(rest, connect, args.zenoh_config, args.zenoh_threads)
    if args.cmd == "ui":
        from ride_machine.rider.ui.app import main as ui_main

        return int(
            ui_main(
                rest,
                connect=connect,
                zenoh_config=args.zenoh_config,
                machine=args.machine,
                zenoh_threads=args.zenoh_threads,
            )
        )
    return _run(args, connect)


def _fastdata(args: argparse.Namespace, rest: list[str]) -> int | None:
    """`rider fastdata …` reads the UDP stream; `rider fastdata set …` writes a user register,
    an online parameter, over Zenoh like `params set` (None: run that)."""
    from .fastdata import SET_COMMANDS, parse_set
    from .fastdata import main as fastdata_main

    if not rest or rest[0] not in SET_COMMANDS:
        return int(fastdata_main(rest))
    reg = parse_set(rest)
    args.cmd, args.params_cmd, args.func = "params", "set", parsers.SET_PARAM
    args.name, args.value, args.persist = reg.name, reg.value, reg.persist
    return None


def _run(args: argparse.Namespace, connect: list[str]) -> int:
    """Run the sub-command's handler on a Rider; an error that ends it becomes its exit code.

    The session opens before the client and the wire models load (Zenoh alone), and without
    `--machine` the default machine's lookup starts at once on its own thread: its settle
    window (rider/discovery.py) runs while Python imports the rest, instead of after."""
    from .discovery import MOTION_SETTLE_S, SETTLE_S, Lookahead
    from .link import Link

    link: Link | None = None
    lookahead: Lookahead | None = None
    try:
        # A one-shot command that exits at once supervises nothing; `--wait` and live views do.
        supervise = bool(getattr(args, "wait", False)) or args.cmd == "watch"
        link = Link(
            args.zenoh_config,
            connect,
            None,
            key_prefix=args.prefix,
            timeout=args.timeout,
            retries=1,
            supervise=supervise,
            zenoh_threads=args.zenoh_threads,
        )
        link.open()
        if args.machine is None:
            settle = MOTION_SETTLE_S if getattr(args, "sends_command", False) else SETTLE_S
            lookahead = Lookahead(settle, link.lookup)
        from .blocking import Rider  # the client, loaded while the lookup settles

        with Rider.on_link(link, args.machine, lookahead) as rider:
            code: int = args.func(args, rider)
            return code
    except (UsageError, RiderError) as exc:
        return _failed(exc, args.json)
    except KeyboardInterrupt:
        return EXIT_OK
    except BrokenPipeError:
        # `rider … | head`: the reader has gone; stop quietly, and keep the interpreter's own
        # final flush of stdout from raising again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK
    finally:
        if lookahead is not None:
            lookahead.join()  # a handler that ended before it needed the machine
        if link is not None:
            link.close()


def _failed(exc: Exception, as_json: bool) -> int:
    """Say on stderr why the command ended (with `--json`, a refusal's reply on stdout too);
    its exit code (`EXITS`)."""
    if isinstance(exc, CommandRefused):
        if as_json:
            print(exc.reply.model_dump_json())
        print(f"rider: refused: {printable(str(exc))}", file=sys.stderr)
    elif isinstance(exc, DuplicateMachine):
        print(f"rider: {printable(str(exc))}", file=sys.stderr)
    else:
        print(f"rider: {exc}", file=sys.stderr)
    return next(code for kinds, code in EXITS if isinstance(exc, kinds))


def entry() -> None:
    """The `rider` command as a process: `main`, its output flushed, then the process ends
    without the interpreter's teardown. Zenoh's own threads may deliver a last callback (a
    query's end or drop) after the session closed; one that arrives while Python finalizes is
    stopped by Python's thread exit, which unwinds through Zenoh's frames and aborts the
    process (`FATAL: exception not rethrown`, exit -6: 2 commands in a suite of 2705 beside
    two CPU-bound processes, after they had answered). Nothing is left to tear down by then:
    the session is closed and the output written. (Tests call `main` in-process.)"""
    try:
        code = main()
    except SystemExit as exc:  # argparse's usage errors and --help, as the interpreter ends them
        code = exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 1
        if exc.code is not None and not isinstance(exc.code, int):
            print(exc.code, file=sys.stderr)
    except BaseException:  # noqa: BLE001 - reported as the interpreter would, then the exit
        traceback.print_exc()
        code = 1
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    os._exit(code)


if __name__ == "__main__":
    entry()
