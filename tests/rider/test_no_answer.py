"""A machine that is reached but does not answer (a frozen daemon: SIGSTOP, a stalled host).

Zenoh ends such a query with an error reply of its own (`Timeout`, zenoh/string) instead of no
reply at all. That is no answer from the machine: `MachineTimeout` and exit code 3, as for a
machine that is down, never a refusal (exit 1) or an unreadable reply. A real Zenoh session on
127.0.0.1 plays the frozen daemon: its queryable takes every query and never answers.
"""

from __future__ import annotations

import json
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from ride_machine.rider import cli
from ride_machine.rider.client import MachineTimeout, Rider
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


FROZEN_PEER_CONFIG = """{
  mode: "peer",
  scouting: { multicast: { enabled: false }, gossip: { enabled: false } },
  transport: { unicast: { open_timeout: 1000 } },
}
"""
"""The test config with a 1 s handshake bound (Zenoh's default is 10 s), to keep this fast."""


def test_a_frozen_peer_is_not_blamed_on_the_login(tmp_path: Path) -> None:
    """A frozen daemon's port still accepts TCP (the kernel does it) but its Zenoh never
    answers the handshake: the hint says so, instead of "authentication refused?" (which is
    for a live listener that rejects the session)."""
    conf = tmp_path / "zenoh.json5"
    conf.write_text(FROZEN_PEER_CONFIG)
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(8)  # accepted by the kernel, never read: a stopped process
        endpoint = f"tcp/127.0.0.1:{listener.getsockname()[1]}"
        rider = Rider("m1", connect=[endpoint], zenoh_config_path=conf, timeout=TIMEOUT_S)
        with rider, pytest.raises(MachineTimeout) as stopped:
            rider.status()
    message = str(stopped.value)
    assert "never answers" in message and "authentication" not in message, message
