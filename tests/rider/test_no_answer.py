"""A machine that is reached but does not answer (a frozen daemon: SIGSTOP, a stalled host).

Zenoh ends such a query with an error reply of its own (`Timeout`, zenoh/string) instead of no
reply at all. That is no answer from the machine: `MachineTimeout` and exit code 3, as for a
machine that is down, never a refusal (exit 1) or an unreadable reply. A real Zenoh session on
127.0.0.1 plays the frozen daemon: its queryable takes every query and never answers.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from rider import cli
from rider.client import MachineTimeout, Rider
from tests.procs import free_port, write_zenoh_config

TIMEOUT_S = 0.3
"""The Rider's query timeout in these tests."""


@pytest.fixture
def frozen() -> Iterator[str]:
    """A peer whose `machine/m1/**` queryable swallows every query; its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    held: list[zenoh.Query] = []
    lock = threading.Lock()

    def swallow(query: zenoh.Query) -> None:
        with lock:
            held.append(query)  # kept, never answered: the caller's query runs into its timeout

    with zenoh.open(conf) as session:
        queryable = session.declare_queryable("machine/m1/**", swallow)
        try:
            yield endpoint
        finally:
            queryable.undeclare()
            with lock:
                for query in held:
                    query.drop()


def test_a_machine_that_never_answers_is_a_timeout(frozen: str, tmp_path: Path) -> None:
    conf = write_zenoh_config(tmp_path)
    with Rider("m1", connect=[frozen], zenoh_config_path=conf, timeout=TIMEOUT_S) as rider:
        with pytest.raises(MachineTimeout, match="machine/m1/status"):
            rider.status()
        with pytest.raises(MachineTimeout, match="machine/m1/cmd/home"):
            rider.home()
        with pytest.raises(MachineTimeout, match="done/"):
            rider.recent_completions()  # not an empty list: nobody said there is none


def test_cli_exits_3_when_the_machine_never_answers(
    frozen: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    conf = str(write_zenoh_config(tmp_path))
    base = ["--connect", frozen, "--zenoh-config", conf, "--machine", "m1"]
    for command in (["status"], ["home"]):
        code = cli.main([*base, "--timeout", str(TIMEOUT_S), *command])
        err = capsys.readouterr().err
        assert code == cli.EXIT_NO_REPLY, err
        assert "no reply" in err and "Timeout" not in err, err
