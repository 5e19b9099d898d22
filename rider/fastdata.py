"""FastData client: ask a machine for axis records over UDP, and the `rider fastdata` command."""

from __future__ import annotations

import argparse
import json
import math
import socket
import sys
import time
from collections.abc import Iterable, Sequence
from typing import TextIO

from ride_machine.schema.axes import PnStatus
from ride_machine.schema.fastdata import (
    DEFAULT_PORT,
    MAX_REQUEST_BYTES,
    USER_REGISTER_LENGTH,
    FastAxisData,
    FastDataError,
    ServerData,
    decode,
)

MAX_REPLY_BYTES = 65535

EXIT_OK = 0
EXIT_NO_DATA = 1
EXIT_USAGE = 2


class FastDataUnavailable(Exception):
    """No usable reply: nothing answered in time, the port refused, or the reply was unreadable."""


def axis_mask(axes: Iterable[int] | None = None) -> bytes:
    """The request naming axis numbers `axes` (1..256: cell i asks for axis i + 1, as in
    seed 002; 1 is rotate, 2 tilt); None asks for every axis."""
    if axes is None:
        return b"\x01" * MAX_REQUEST_BYTES
    wanted = set(axes)
    bad = sorted(a for a in wanted if not 1 <= a <= MAX_REQUEST_BYTES)
    if bad:
        raise ValueError(f"axis number {bad[0]} outside 1..{MAX_REQUEST_BYTES}")
    if not wanted:
        raise ValueError("name at least one axis")
    return bytes(1 if i + 1 in wanted else 0 for i in range(max(wanted)))


class FastDataClient:
    """A UDP socket connected to one server; `query()` sends a mask and decodes the reply."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, timeout: float = 1.0):
        self.address = (host, port)
        self.timeout = timeout
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._sock = socket.socket(family, socket.SOCK_DGRAM)
        # Connected: datagrams from anyone but the server are dropped by the kernel.
        self._sock.connect(self.address)

    def query(self, axes: Iterable[int] | None = None) -> ServerData:
        """One request → one decoded reply; raises `FastDataUnavailable` on timeout or bad data."""
        self._discard_late_replies()
        self._sock.settimeout(self.timeout)
        try:
            self._sock.send(axis_mask(axes))
            data = self._sock.recv(MAX_REPLY_BYTES)
        except TimeoutError as exc:
            raise FastDataUnavailable(
                f"no reply from {self._where()} within {self.timeout} s"
            ) from exc
        except ConnectionRefusedError as exc:
            raise FastDataUnavailable(f"nothing listens on {self._where()}") from exc
        try:
            return decode(data)
        except FastDataError as exc:
            raise FastDataUnavailable(f"unreadable reply from {self._where()}: {exc}") from exc

    def _discard_late_replies(self) -> None:
        """Drop replies to earlier, timed-out requests so they are not taken for this one."""
        self._sock.setblocking(False)
        try:
            while True:
                self._sock.recv(MAX_REPLY_BYTES)
        except (BlockingIOError, ConnectionRefusedError):
            pass

    def _where(self) -> str:
        return f"{self.address[0]}:{self.address[1]}"

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> FastDataClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ------------------------------------------------------------------------------------ CLI
_COLUMNS = ("axis", "status", "drvStat", "cycle", "pCmd", "pFb", "cCmd", "cFb", "vCmd", "vFb")


def status_flags(pn_status: int) -> str:
    """`pnStatus` as flag names, e.g. `moving,enabled`; unknown bits shown in hex."""
    names = [
        label
        for bit, label in (
            (PnStatus.SETTLED, "settled"),
            (PnStatus.MOVING, "moving"),
            (PnStatus.DRIVE_ENABLED, "enabled"),
            (PnStatus.DRIVE_FAULT, "FAULT"),
            (PnStatus.POSITION_UNKNOWN, "unknown"),
        )
        if pn_status & bit
    ]
    rest = pn_status & ~0x1F
    if rest:
        names.append(hex(rest))
    return ",".join(names) or "-"


def format_header() -> str:
    return f"{_COLUMNS[0]:>4} {_COLUMNS[1]:<24} {_COLUMNS[2]:>7} {_COLUMNS[3]:>10}" + "".join(
        f" {c:>10}" for c in _COLUMNS[4:]
    )


def format_row(r: FastAxisData) -> str:
    flags = status_flags(r.pnStatus)
    return f"{r.axisnumber:>4} {flags:<24} {r.drvStat:>7} {r.bus_cycle_num:>10}" + "".join(
        f" {v + 0.0:>10.3f}"  # + 0.0 turns -0.0 into 0.0
        for v in (r.pCmd, r.pFb, r.cCmd, r.cFb, r.vCmd, r.vFb)
    )


def format_registers(reply: ServerData) -> str:
    """The user registers, one line per array."""
    ints = " ".join(str(i) for i in reply.ints)
    doubles = " ".join(f"{d:g}" for d in reply.doubles)
    return f"int_array: {ints}\ndouble_array: {doubles}"


def format_json(reply: ServerData, r: FastAxisData) -> str:
    """One record as a JSON line, every field, with the header version it came with."""
    return json.dumps({"version": reply.version, **r.as_dict()})


def format_json_registers(reply: ServerData) -> str:
    return json.dumps({"int_array": list(reply.ints), "double_array": list(reply.doubles)})


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The `rider fastdata` options, for a parent CLI that adds this as a subcommand."""
    p.add_argument("--host", default="127.0.0.1", help="machine address (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="UDP port (default 60000)")
    p.add_argument(
        "--axis",
        type=int,
        action="append",
        dest="axes",
        metavar="N",
        help="axis number to ask for (repeatable; 1 rotate, 2 tilt); default every axis",
    )
    p.add_argument(
        "--registers", action="store_true", help="also print the user registers (int/double)"
    )
    p.add_argument("--timeout", type=float, default=1.0, help="seconds to wait for each reply")
    p.add_argument("--watch", action="store_true", help="keep polling and stream the records")
    p.add_argument("--interval", type=float, default=0.1, help="seconds between polls (--watch)")
    p.add_argument("--count", type=int, help="with --watch: stop after this many polls")
    p.add_argument("--json", action="store_true", help="one JSON object per record and line")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="rider fastdata",
        description="Read FastData axis records. `rider fastdata set-int|set-double INDEX VALUE"
        " [--persist]` sets a user register (over Zenoh, as online parameter"
        " fastdata.int.INDEX / fastdata.double.INDEX).",
    )
    add_arguments(p)
    return p


SET_COMMANDS = {"set-int": "int", "set-double": "double"}
"""`rider fastdata set-int|set-double`: the register kind each writes."""


def parse_set(argv: Sequence[str]) -> argparse.Namespace:
    """`set-int INDEX VALUE [--persist]` → the online parameter name and value to write."""
    p = argparse.ArgumentParser(
        prog=f"rider fastdata {argv[0]}",
        description="Set a FastData user register; every reply carries it from the next request.",
    )
    p.add_argument("index", type=int, help=f"register index 0..{USER_REGISTER_LENGTH - 1}")
    p.add_argument("value", help="an int32 (set-int) or a finite number (set-double)")
    p.add_argument("--persist", action="store_true", help="keep it across restarts")
    args = p.parse_args(argv[1:])
    if not 0 <= args.index < USER_REGISTER_LENGTH:
        p.error(f"index {args.index} outside 0..{USER_REGISTER_LENGTH - 1}")
    args.name = f"fastdata.{SET_COMMANDS[argv[0]]}.{args.index}"
    return args


def run(args: argparse.Namespace, out: TextIO | None = None, err: TextIO | None = None) -> int:
    """Run parsed `rider fastdata` options; returns the exit code."""
    out = out or sys.stdout
    err = err or sys.stderr
    problem = _check(args)
    if problem:
        print(f"rider fastdata: {problem}", file=err)
        return EXIT_USAGE
    polls = args.count if args.watch else 1
    got = 0
    n = 0
    try:
        client = FastDataClient(args.host, args.port, args.timeout)
    except OSError as exc:  # a host name that does not resolve, an address of no family
        print(
            f"rider fastdata: cannot reach {args.host}:{args.port}: {exc.strerror or exc}", file=err
        )
        return EXIT_NO_DATA
    with client:
        try:
            while polls is None or n < polls:
                if n and args.watch:
                    time.sleep(args.interval)
                n += 1
                try:
                    reply = client.query(args.axes)
                except FastDataUnavailable as exc:
                    print(f"rider fastdata: {exc}", file=err)
                    continue
                if not args.json and got == 0:
                    print(format_header(), file=out)
                got += 1
                for r in reply.axes:
                    print(format_json(reply, r) if args.json else format_row(r), file=out)
                if args.registers:
                    regs = format_json_registers(reply) if args.json else format_registers(reply)
                    print(regs, file=out)
                out.flush()
        except KeyboardInterrupt:
            pass  # Ctrl-C ends a watch normally
    return EXIT_OK if got else EXIT_NO_DATA


def _check(args: argparse.Namespace) -> str | None:
    if not 0 < args.port < 65536:
        return f"--port {args.port} outside 1..65535"
    if not (0 < args.timeout < math.inf):  # NaN too
        return "--timeout must be > 0 and finite"
    if not (0 <= args.interval < math.inf):
        return "--interval must be >= 0 and finite"
    if args.count is not None and args.count < 1:
        return "--count must be >= 1"
    if args.axes is not None:
        try:
            axis_mask(args.axes)
        except ValueError as exc:
            return str(exc)
    return None


def main(argv: Sequence[str] | None = None) -> int:
    """`rider fastdata …`: print the records once, or stream them with `--watch`."""
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
