"""Bad global options of the `rider` CLI are bad usage (exit 2, one line on stderr), caught
before any Zenoh call: an empty or multi-part machine id, a timeout that is not a positive
finite number. No machine is needed (nothing listens at the endpoint)."""

from __future__ import annotations

import pytest

from ride_machine.rider import cli
from tests.procs import free_port


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("--machine", ""),
        ("--machine", "m1/cmd"),
        ("--machine", "/m1"),
        ("--timeout", "-1"),
        ("--timeout", "0"),
        ("--timeout", "nan"),
        ("--timeout", "inf"),
        ("--zenoh-threads", "-1"),
        ("--zenoh-threads", "65"),
        ("--zenoh-threads", "two"),
    ],
)
def test_bad_global_option_is_usage_error(
    option: str, value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(SystemExit) as stopped:
        cli.main(["--connect", endpoint, option, value, "status"])
    assert stopped.value.code == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert f"argument {option}" in err and "Traceback" not in err, err


@pytest.mark.parametrize(
    "words",
    [
        ["tilt_ai", "forzen"],  # a typo: sent as "no fault", it cleared the tilt signal faults
        ["tilt_ai", "frozen", "-3"],
        ["stall", "tilt", "of"],  # a typo of `off`: it stalled the axis
        ["estop", "now"],
        ["home", "rotate", "open", "extra"],
    ],
)
def test_a_sim_argument_the_cli_does_not_know_is_usage_error(
    words: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    code = cli.main(["--connect", endpoint, "--machine", "m1", "--timeout", "0.3", "sim", *words])
    err = capsys.readouterr().err
    assert code == cli.EXIT_USAGE, err
    assert f"sim {words[0]}" in err, err


@pytest.mark.parametrize("tid", ["a*", "**", "a//b", "@x", "x" * 65, "a b"])
def test_a_transaction_id_no_machine_can_have_is_usage_error(
    tid: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """`rider done TID` with an id the wire format forbids (a wildcard, an empty part…) was a
    Zenoh key error (exit 1) or a wildcard query; it is bad input, caught before the query."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(SystemExit) as stopped:
        cli.main(["--connect", endpoint, "--machine", "m1", "done", tid])
    assert stopped.value.code == cli.EXIT_USAGE
    assert "transaction_id" in capsys.readouterr().err
