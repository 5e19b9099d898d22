"""`rider gateway`: its options, and the process around the gateway (signals, exit codes)."""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from ride_machine.rider.client import BadCredentials, BadRuntime, MachineTimeout
from ride_machine.rider.exits import own_options
from ride_machine.rider.gateway import nodeset_cache

from .identity import Limits
from .security import BadUsers, read_certificates, read_users
from .server import Gateway, Options

log = logging.getLogger(__name__)

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2


def _address(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} is not HOST:PORT")
    return host.strip("[]"), int(port)


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0 < value <= 3600:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds (0-3600]")
    return value


def _count(text: str) -> int:
    if not text.isdigit() or not 1 <= int(text) <= 10_000:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number from 1 to 10000")
    return int(text)


def _session_options(p: argparse.ArgumentParser) -> None:
    """How long sessions and machines are kept, and how many sessions at once."""
    p.add_argument(
        "--session-timeout",
        type=_seconds,
        default=10.0,
        help="longest OPC UA session timeout granted, s (default 10): a motion"
        " started through OPC UA pauses this long plus the rider-loss timeout after"
        " its client went silent",
    )
    p.add_argument(
        "--forget-after",
        type=_seconds,
        default=30.0,
        help="a machine gone this long leaves the address space (default 30 s)",
    )
    p.add_argument(
        "--max-sessions",
        type=_count,
        default=Limits.sessions,
        help=f"OPC UA sessions served at once (default {Limits.sessions}); more are refused",
    )


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="rider gateway",
        description="Every machine on the bus in OPC UA (SCADA) and Prometheus (docs/plant.md).",
    )
    p.add_argument(
        "--opcua",
        type=_address,
        default=("127.0.0.1", 4840),
        help="OPC UA endpoint HOST:PORT (default 127.0.0.1:4840)",
    )
    p.add_argument(
        "--metrics",
        type=_address,
        default=("127.0.0.1", 9464),
        help="Prometheus endpoint HOST:PORT (default 127.0.0.1:9464)",
    )
    p.add_argument("--no-metrics", action="store_true", help="serve no metrics endpoint")
    p.add_argument(
        "--monitor",
        action="store_true",
        help="read-only: every method call is refused; give it the monitor login"
        " (RIDER_ZENOH_USER=monitor) under the ACL profiles",
    )
    p.add_argument(
        "--users",
        type=Path,
        help="operators: a file of user:password lines (none: nobody may call)",
    )
    p.add_argument(
        "--operator-certs",
        type=Path,
        help="a directory of certificates (DER or PEM) that log in as operators",
    )
    p.add_argument(
        "--certificate",
        type=Path,
        help="the gateway's certificate (DER or PEM): adds the Sign and Sign & Encrypt"
        " endpoints (Basic256Sha256, Aes128_Sha256_RsaOaep, Aes256_Sha256_RsaPss) and the"
        " operators' logins (made by `machine credentials init`)",
    )
    p.add_argument("--private-key", type=Path, help="the certificate's private key (PEM)")
    _session_options(p)
    p.add_argument(
        "--cache-dir",
        type=Path,
        help="where the OPC UA standard nodes are kept on disk, read as needed (default"
        " $XDG_CACHE_HOME/ride-machine or ~/.cache/ride-machine, else <tmp>/ride-machine-<uid>)",
    )
    p.add_argument(
        "--no-cache",
        action="store_true",
        help="hold the standard nodes in memory (about 50 MB more)",
    )
    p.add_argument("--prefix", default="machine", help="key prefix (default: machine)")
    p.add_argument("--timeout", type=_seconds, default=2.0, help="command reply timeout, s")
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    return p


def options_from(
    args: argparse.Namespace, connect: list[str], zenoh_config: Path | None, zenoh_threads: int
) -> Options:
    """The gateway's options; `BadUsers` or `OSError` for a file that cannot be used."""
    if (args.certificate is None) != (args.private_key is None):
        raise BadUsers("--certificate and --private-key go together")
    if (args.users or args.operator_certs) and args.certificate is None:
        # The password is encrypted with it; a user certificate signs with its policy.
        raise BadUsers(
            "--users and --operator-certs need --certificate and --private-key: an operator's"
            " password or certificate is never accepted unprotected"
        )
    return Options(
        connect=connect,
        zenoh_config=zenoh_config,
        opcua=args.opcua,
        metrics=None if args.no_metrics else args.metrics,
        read_only=args.monitor,
        users=read_users(args.users) if args.users else {},
        operator_certs=read_certificates(args.operator_certs) if args.operator_certs else {},
        certificate=args.certificate,
        private_key=args.private_key,
        session_timeout_s=args.session_timeout,
        forget_after_s=args.forget_after,
        command_timeout_s=args.timeout,
        prefix=args.prefix,
        zenoh_threads=zenoh_threads,
        max_sessions=args.max_sessions,
        cache_dirs=_cache_dirs(args),
    )


def _cache_dirs(args: argparse.Namespace) -> tuple[Path, ...]:
    if args.no_cache:
        return ()
    return (args.cache_dir,) if args.cache_dir is not None else nodeset_cache.default_dirs()


async def _serve(options: Options) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await Gateway(options).run(stop)


def main(
    argv: Sequence[str],
    connect: list[str],
    zenoh_config: Path | None,
    zenoh_threads: int = 1,
) -> int:
    """Serve until SIGTERM/SIGINT; the Zenoh session is closed before returning."""
    args = own_options(build_parser(), argv)
    if isinstance(args, int):
        return args
    # asyncua logs every session and call at INFO; the gateway's own lines say what matters.
    logging.getLogger("asyncua").setLevel(max(logging.WARNING, logging.getLogger().level))
    if os.environ.get("RIDER_ZENOH_USER") == "monitor" and not args.monitor:
        # The ACL drops a monitor's commands unanswered: every call would end BadTimeout.
        log.warning("event=monitor_login_commands hint=add --monitor for a read-only gateway")
    try:
        options = options_from(args, connect, zenoh_config, zenoh_threads)
        asyncio.run(_serve(options))
    except (BadUsers, OSError, BadCredentials, BadRuntime) as exc:
        print(f"rider gateway: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except MachineTimeout as exc:
        print(f"rider gateway: {exc}", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK
