"""The `machine` command: run the daemon, check a config, or watch one session in the terminal."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, TextIO

from ride_machine.hal.backends import names
from ride_machine.schema.findings import Findings, Severity
from ride_machine.service.config.load import load, override_source
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.config.validate import finding_line, findings_of, hardware_findings

from .logfmt import flush_logs, setup_logging
from .signals import dump_stacks_on_signal

if TYPE_CHECKING:
    from ride_machine.service.supervision.assembly import DaemonOptions

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_CONFIG = 2


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, help="machine config (TOML); project defaults if omitted")
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])


def _add_hal_args(p: argparse.ArgumentParser) -> None:
    hal = p.add_mutually_exclusive_group()
    hal.add_argument("--sim", action="store_const", const="sim", dest="hal", help="simulator HAL")
    hal.add_argument(
        "--hal",
        choices=sorted(names()),
        help="HAL backend, any registered (overrides hal.backend)",
    )


def _add_run_args(run: argparse.ArgumentParser) -> None:
    """What `run` takes; `supervise` takes the same and passes the result to its child."""
    _add_config_args(run)
    _add_hal_args(run)
    run.add_argument("--zenoh-config", type=Path, help="zenoh.json5 to open the session with")
    run.add_argument(
        "--listen",
        action="append",
        default=[],
        help="Zenoh listen endpoint (repeatable; replaces the config file's)",
    )
    run.add_argument(
        "--connect",
        action="append",
        default=[],
        help="Zenoh connect endpoint (repeatable; replaces the config file's)",
    )
    _add_override_args(run)
    run.add_argument("--data-dir", type=Path, help="override data_dir")
    run.add_argument("--fastdata", action="store_true", help="serve the FastData UDP axis stream")


def _add_override_args(p: argparse.ArgumentParser) -> None:
    # Plain strings: a bad value is a finding of the one config check, like a bad file value.
    p.add_argument("--id", dest="machine_id", help="override machine.id")
    p.add_argument("--period", help="override loop.period_s (seconds)")


OVERRIDE_OPTIONS = {
    "/hal/backend": "--hal",
    "/machine/id": "--id",
    "/loop/period_s": "--period",
    "/data_dir": "--data-dir",
    "/fastdata/enabled": "--fastdata",
}
"""The config field each command-line override sets (findings name the option)."""


def overrides_of(args: argparse.Namespace) -> dict[str, object]:
    """The command-line overrides given, as config pointers (applied before validation)."""
    out: dict[str, object] = {}
    if getattr(args, "hal", None):
        out["/hal/backend"] = args.hal
    if getattr(args, "machine_id", None) is not None:
        out["/machine/id"] = args.machine_id
    if getattr(args, "period", None) is not None:
        out["/loop/period_s"] = _number(args.period)
    if getattr(args, "data_dir", None) is not None:
        out["/data_dir"] = str(args.data_dir)
    if getattr(args, "fastdata", False):
        out["/fastdata/enabled"] = True
    return out


def _number(text: str) -> object:
    """A float if it is one; else the text, for the config check to report as a wrong type."""
    try:
        return float(text)
    except ValueError:
        return text


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="machine", description=__doc__)
    sub = parser.add_subparsers(dest="cmd", required=True)
    _add_run_and_supervise(sub)
    val = sub.add_parser("validate", help="check a machine config and print every finding")
    _add_config_args(val)
    _add_hal_args(val)
    _add_override_args(val)
    val.add_argument("--json", action="store_true", help="print the findings as JSON")
    val.set_defaults(handler=_validate_command)
    _add_credentials(sub)
    _add_events(sub)
    sch = sub.add_parser("schema", help="write the wire contract as JSON Schema (+ keys.json)")
    sch.add_argument(
        "directory",
        nargs="?",
        type=Path,
        default=Path("schema/json"),
        help="where to write it (default schema/json)",
    )
    sch.set_defaults(handler=_schema)
    demo = sub.add_parser("demo", help="same as `run --sim --once-session`")
    _add_config_args(demo)
    demo.add_argument("--speed", type=float, default=1.0, help="simulated seconds per second")
    demo.set_defaults(handler=_with_config(_demo))
    return parser


def _add_run_and_supervise(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    run = sub.add_parser("run", help="run the machine daemon")
    _add_run_args(run)
    run.add_argument(
        "--once-session",
        action="store_true",
        help="no network: calibrate, home and run the default session once, then exit",
    )
    run.add_argument("--speed", type=float, default=1.0, help="with --once-session: sim speed-up")
    run.set_defaults(handler=_with_config(_run))

    sup = sub.add_parser(
        "supervise",
        help="run the daemon as a child: outputs safe, FAULT_HW and a restart when it dies",
    )
    _add_run_args(sup)
    sup.add_argument("--backoff", type=float, default=0.5, help="first restart delay (s)")
    sup.add_argument("--backoff-max", type=float, default=8.0, help="longest restart delay (s)")
    sup.add_argument(
        "--hang",
        type=float,
        default=None,
        help="kill and restart a daemon whose scan has not cycled for this long (s; default:"
        " 1 s, or 3 watchdog limits when that is longer)",
    )
    sup.add_argument(
        "--plant",
        type=Path,
        default=None,
        metavar="DIR",
        help="with --sim: attach to a simulated plant already running in DIR (python -m"
        " sim.plant --make-image, a container of its own) instead of starting one",
    )
    sup.set_defaults(handler=_with_config(_supervise))


def _add_credentials(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    cred = sub.add_parser("credentials", help="make the Zenoh login files of the ACL profiles")
    cred_sub = cred.add_subparsers(dest="cred_cmd", required=True)
    init = cred_sub.add_parser(
        "init",
        help="random passwords for the machine, each operator station and the monitor, and the"
        " dictionary",
    )
    init.add_argument("directory", type=Path, help="where to write them (created 0700)")
    init.add_argument(
        "--stations",
        "--station",
        action="append",
        default=[],
        metavar="NAME[,NAME…]",
        help="operator stations, a login each (besides the stack's own: ui, gateway); the"
        " profiles make every login of the dictionary a station",
    )
    init.add_argument(
        "--shared-rider",
        action="store_true",
        help="also the one `rider` login several stations share (not recommended: a station on"
        " it can keep another's dead Rider alive; the machine warns at start)",
    )
    init.add_argument("--force", action="store_true", help="replace existing files")
    init.set_defaults(handler=_credentials)


def _add_events(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    ev = sub.add_parser("events", help="the event history, offline (reads <data_dir>/events.db)")
    evs = ev.add_subparsers(dest="events_cmd", required=True)
    exp = evs.add_parser("export", help="write events as CSV or JSON lines")
    _add_config_args(exp)
    exp.add_argument("--data-dir", type=Path, help="override data_dir")
    exp.add_argument("--since", help="a seq number, an age (30m, 12h, 7d) or a local time")
    exp.add_argument("--until", help="as --since")
    exp.add_argument("--kind", action="append", default=[], help="only these kinds (repeatable)")
    exp.add_argument("--format", choices=["csv", "jsonl"], default="jsonl")
    exp.add_argument("--output", "-o", type=Path, help="file to write (default: stdout)")
    exp.set_defaults(handler=_with_config(_events))


def load_config(
    path: Path | None, overrides: dict[str, object] | None = None, stream: TextIO = sys.stderr
) -> MachineConfig | None:
    """The config with its overrides, or None after printing every finding (exit code 2).

    Each finding is a line naming where the value came from: the file, or the option.
    """
    config, findings = load(path, overrides)
    given = {k: v for k, v in OVERRIDE_OPTIONS.items() if k in (overrides or {})}
    for f in findings.findings:
        print(finding_line(override_source(f, given, str(path or "machine")), f), file=stream)
    return config


def check_hardware(config: MachineConfig, source: str, stream: TextIO = sys.stderr) -> bool:
    """Print the host check's findings (`hardware_findings`); False when any is an error."""
    found = hardware_findings(config)
    for f in found:
        print(finding_line(source, f), file=stream)
    return findings_of(found).ok


def print_findings(findings: Findings, path: Path | None, as_json: bool) -> None:
    if as_json:
        print(json.dumps(findings.model_dump(mode="json"), indent=2))
        return
    if not findings.findings:
        print(f"{path or 'defaults'}: ok, no findings")
    for f in findings.findings:
        print(f"{f.severity:7} {f.category:14} {f.path or '/':32} {f.message}")
    if findings.findings:
        errors = sum(f.severity is Severity.ERROR for f in findings.findings)
        warnings = len(findings.findings) - errors
        verdict = "the daemon will not start" if errors else "the daemon will start"
        print(f"{path or 'defaults'}: {errors} error(s), {warnings} warning(s); {verdict}")


def credentials_init(
    directory: Path, force: bool, stations: Sequence[str] = (), shared: bool = False
) -> int:
    """`machine credentials init`: `stations` as given (each a name or a comma list)."""
    from ride_machine.service.adapters.credentials import (
        DICTIONARY,
        CredentialsExist,
        identities,
        init_credentials,
        password_file,
    )

    opcua = _opcua_credentials()
    try:
        existing = [str(p) for p in opcua.opcua_files(directory) if p.exists()] if opcua else []
        if existing and not force:
            raise CredentialsExist(f"{', '.join(existing)}: exists already (--force replaces)")
        names = tuple(n.strip() for arg in stations for n in arg.split(",") if n.strip())
        users = identities(names, shared=shared)
        # The plant gateway's too (docs/plant.md), in the same set: all new, or none.
        gateway = opcua.opcua_new_files(directory) if opcua is not None else []
        written = init_credentials(directory, users, force=force, also=gateway)
    except (CredentialsExist, OSError, ValueError) as exc:
        print(f"machine: credentials: {exc}", file=sys.stderr)
        return EXIT_FAILED
    for path in written:
        print(f"wrote {path}")
    # As given, not resolved: run in a container, a resolved path would be the container's.
    d = directory
    riders = users[1:-1]
    lines = [
        f"machine: MACHINE_ZENOH_DICTIONARY_FILE={d / DICTIONARY} machine run --zenoh-config"
        " zenoh/acl.json5",
        *(
            f"{label:8} RIDER_ZENOH_USER={u} RIDER_ZENOH_PASSWORD_FILE={password_file(d, u)}"
            for label, u in [*(("station:", u) for u in riders), ("monitor:", "monitor")]
        ),
        _gateway_hint(d, opcua),
    ]
    print("\n".join(lines))
    return EXIT_OK


def _opcua_credentials() -> ModuleType | None:
    """The gateway's OPC UA credentials module; None where the gateway's libraries are not
    installed (the machine's image: docs/deploy.md)."""
    try:
        from .adapters import opcua_credentials
    except ModuleNotFoundError as exc:
        if exc.name != "cryptography":
            raise
        return None
    return opcua_credentials


def _gateway_hint(d: Path, opcua: ModuleType | None) -> str:
    if opcua is None:
        return (
            "gateway: its OPC UA files not made: this installation has no gateway libraries"
            " (with the plant gateway, run this command in its image: docs/deploy.md)"
        )
    return (
        f"gateway: rider gateway --users {d / opcua.USERS} --certificate {d / opcua.CERTIFICATE}"
        f" --private-key {d / opcua.PRIVATE_KEY} (as station gateway)"
    )


def main(argv: list[str] | None = None) -> int:
    try:
        return _main(argv)
    finally:
        flush_logs()  # every line written before `machine …` returns (also in-process)


def _main(argv: list[str] | None) -> int:
    args = build_parser().parse_args(argv)
    handler: Handler = args.handler
    return handler(args)


Handler = Callable[[argparse.Namespace], int]
"""What a sub-command does with its parsed arguments (each parser's `handler` default)."""


def _credentials(args: argparse.Namespace) -> int:
    return credentials_init(args.directory, args.force, args.stations, args.shared_rider)


def _schema(args: argparse.Namespace) -> int:
    from ride_machine.schema.jsonschema import write

    try:
        paths = write(args.directory)
    except OSError as exc:  # a read-only or missing place, a file where the directory goes
        where = exc.filename or args.directory
        print(f"machine: cannot write the schema to {where}: {exc.strerror}", file=sys.stderr)
        return EXIT_FAILED
    print(f"machine: wrote {len(paths)} files to {args.directory}")
    return EXIT_OK


def _validate_command(args: argparse.Namespace) -> int:
    setup_logging(args.log_level)
    return _validate(args.config, overrides_of(args), args.json)


def _with_config(run: Callable[[argparse.Namespace, MachineConfig], int]) -> Handler:
    """A handler that logs at the asked level and runs `run` on the config with the
    command-line overrides, or exits 2 after printing every finding."""

    def handler(args: argparse.Namespace) -> int:
        setup_logging(args.log_level)
        config = load_config(args.config, overrides_of(args))
        return EXIT_CONFIG if config is None else run(args, config)

    return handler


def _events(args: argparse.Namespace, config: MachineConfig) -> int:
    from ride_machine.service.adapters.export import export_events

    return export_events(args, args.data_dir or Path(config.data_dir))


def _demo(args: argparse.Namespace, config: MachineConfig) -> int:
    from .demo import run_demo

    return run_demo(config, speed=args.speed)


def _run(args: argparse.Namespace, config: MachineConfig) -> int:
    if args.once_session:
        return _demo(args, config)
    from ride_machine.service.supervision.daemon import run_daemon

    dump_stacks_on_signal()  # `kill -USR2 <pid>`: every thread's stack in the log

    # The backend's own check, on the config that will run: the same findings, the same way,
    # for `run` and `supervise`, before anything opens.
    if not check_hardware(config, str(args.config or "machine")):
        return EXIT_CONFIG
    return run_daemon(config, _daemon_options(args))


def _supervise(args: argparse.Namespace, config: MachineConfig) -> int:
    from ride_machine.service.supervision.restarts import SupervisorOptions
    from ride_machine.service.supervision.supervisor import run_supervisor

    dump_stacks_on_signal()
    if not check_hardware(config, str(args.config or "machine")):
        return EXIT_CONFIG
    if not 0 < args.backoff <= args.backoff_max:
        print("machine: need 0 < --backoff <= --backoff-max", file=sys.stderr)
        return EXIT_CONFIG
    if args.hang is not None and not config.loop.watchdog_limit_s < args.hang <= 600:
        print(
            f"machine: --hang must be longer than the watchdog limit"
            f" ({config.loop.watchdog_limit_s:g} s) and at most 600 s",
            file=sys.stderr,
        )
        return EXIT_CONFIG
    sup = SupervisorOptions(
        backoff_s=args.backoff,
        backoff_max_s=args.backoff_max,
        hang_s=args.hang,
        log_level=args.log_level,
        plant_dir=args.plant,
    )
    return run_supervisor(config, _daemon_options(args), sup)


def _daemon_options(args: argparse.Namespace) -> DaemonOptions:
    from ride_machine.service.supervision.assembly import DaemonOptions

    return DaemonOptions(zenoh_config=args.zenoh_config, listen=args.listen, connect=args.connect)


def _validate(path: Path | None, overrides: dict[str, object], as_json: bool) -> int:
    """`machine validate`: the findings `run` would print (file, overrides) and, for the
    backend that would run, the host's."""
    config, findings = load(path, overrides)
    if config is not None:
        findings = findings_of([*findings.findings, *hardware_findings(config)])
    print_findings(findings, path, as_json)
    return EXIT_OK if findings.ok else EXIT_CONFIG


if __name__ == "__main__":
    sys.exit(main())
