"""The `rider` command loads only what a command needs (issue 59, start-up): `--help` and bad
usage are answered from argparse alone, without Zenoh, pydantic or a wire model; a read such as
`rider status` loads the client but not the event history's models, the UI or the gateway.
Each check runs the CLI in a fresh interpreter and reads its `sys.modules` at the end (how long
it takes is bench/startup.py's business, not a test's)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from collections.abc import Iterator

import pytest

from ride_machine.rider import cli
from ride_machine.rider.subcommands import Lazy
from tests.procs import REPO, free_port

PROBE = """
import contextlib, json, sys
from ride_machine.rider.cli import main
code = 0
with contextlib.redirect_stdout(sys.stderr):
    try:
        code = main(sys.argv[1:])
    except SystemExit as exc:
        code = exc.code
print(json.dumps({"code": code, "modules": sorted(sys.modules)}))
"""
"""Runs `rider ARGS` in this interpreter and prints its exit code and every module loaded."""

HEAVY = (
    "zenoh",
    "pydantic",
    "pydantic_core",
    "msgpack",
    "ride_machine.rider.blocking",
    "ride_machine.rider.link",
)
"""What `--help` must not load: the network stack, the validation library and the client."""

NOT_FOR_READS = (
    "ride_machine.rider.ui",
    "ride_machine.rider.gateway",
    "asyncua",
    "starlette",
    "uvicorn",
    "ride_machine.schema.events",
)
"""What a plain read must not load: the UI, the plant gateway and the event history's models."""


def _loaded(*args: str) -> tuple[int, set[str]]:
    """`rider ARGS` in a fresh interpreter: its exit code and the modules it loaded."""
    done = subprocess.run(
        [sys.executable, "-c", PROBE, *args],
        check=False,
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout.splitlines()[-1])
    return int(result["code"]), set(result["modules"])


def _under(modules: set[str], prefixes: tuple[str, ...]) -> list[str]:
    return sorted(m for m in modules if any(m == p or m.startswith(p + ".") for p in prefixes))


@pytest.mark.parametrize(
    "args",
    [["--help"], ["status", "--help"], ["events", "--help"], ["frobnicate"], ["--timeout", "0"]],
)
def test_help_and_bad_usage_load_no_zenoh_no_pydantic_no_client(args: list[str]) -> None:
    code, modules = _loaded(*args)
    assert code in (cli.EXIT_OK, cli.EXIT_USAGE)
    assert _under(modules, HEAVY) == []
    assert _under(modules, ("ride_machine.schema",)) == [
        "ride_machine.schema",
        "ride_machine.schema.event_kinds",
    ]


def test_a_read_loads_the_client_but_not_the_ui_gateway_or_event_models() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nothing listens: no reply, exit 3
    code, modules = _loaded("--connect", endpoint, "--timeout", "0.3", "-m", "m1", "status")
    assert code == cli.EXIT_NO_REPLY
    assert "ride_machine.rider.blocking" in modules and "ride_machine.schema.status" in modules
    assert _under(modules, NOT_FOR_READS) == []


def _handlers(parser: argparse.ArgumentParser) -> Iterator[tuple[str, object]]:
    """Every sub-command's handler (`func`), nested sub-commands too, by its command words."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                func = sub.get_default("func")
                if func is not None:
                    yield name, func
                for deeper, inner in _handlers(sub):
                    yield f"{name} {deeper}", inner


def test_every_sub_command_names_a_handler_that_exists() -> None:
    found = dict(_handlers(cli.build_parser()))
    assert {"status", "start", "events", "params set", "calibration set", "sim"} <= set(found)
    for words, func in found.items():
        assert isinstance(func, Lazy), words
        assert callable(func.load()), words


def test_a_lazy_handler_of_an_unknown_kind_is_refused_at_once() -> None:
    with pytest.raises(ValueError, match="no sub-command kind"):
        Lazy("gateway", "main")
