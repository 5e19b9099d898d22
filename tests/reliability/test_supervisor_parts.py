"""The supervisor's and the credentials' pure parts: no process, no session."""

from __future__ import annotations

import json
import signal
import tomllib
from pathlib import Path

import pytest

from ride_machine.common.credentials import (
    MACHINE,
    RIDER,
    CredentialError,
    env_name,
    zenoh_settings,
)
from ride_machine.hal.revpi import check_revpi_io
from ride_machine.service.bus.supervisor import child_config, requires_credentials, router_config
from ride_machine.service.config.model import HalBackend, MachineConfig
from ride_machine.service.supervision.restarts import Backoff, describe_exit
from ride_machine.service.supervision.toml_out import to_toml
from ride_machine.sim.world import CONFIG_RSC
from tests.reliability.support import ACL_PROFILE

PRIVATE = "unixsock-stream//tmp/machine-sup-x/zenoh.sock"


def test_child_config_round_trips_through_toml() -> None:
    config = MachineConfig().with_overrides(
        machine={"id": "ride-7"},
        loop={"period_s": 0.005, "cpu": 1},
        hal={
            "backend": HalBackend.REVPI,
            "iomap": {"rotateHome": "I_5", "estop_active_low": False},
            "revpi": {"procimg": "/tmp/a b/procimg", "configrsc": '/x/"q".rsc'},
        },
        fastdata={"enabled": True},
    )
    data = config.model_dump(mode="json", by_alias=True, exclude_none=True)
    assert MachineConfig.model_validate(tomllib.loads(to_toml(data))) == config


def test_toml_leaves_out_none_and_refuses_what_it_cannot_write() -> None:
    assert tomllib.loads(to_toml({"a": None, "b": {"c": None, "d": [1, 2.5, "x"]}})) == {
        "b": {"d": [1, 2.5, "x"]}
    }
    with pytest.raises(TypeError):
        to_toml({"a": object()})


@pytest.mark.hazard("H03")
def test_backoff_doubles_to_its_maximum_and_resets_after_a_stable_run() -> None:
    b = Backoff(0.5, 4.0)
    assert [b.delay(1.0, 10.0) for _ in range(5)] == [0.5, 1.0, 2.0, 4.0, 4.0]
    assert b.delay(None, 10.0) == 4.0  # never came up: no reset
    assert b.delay(10.0, 10.0) == 0.5


def test_exit_descriptions_name_the_signal() -> None:
    assert "SIGKILL" in describe_exit(-signal.SIGKILL)
    assert "SIGSEGV" in describe_exit(-signal.SIGSEGV)
    assert "code 3" in describe_exit(3)
    assert "without being asked" in describe_exit(0)


def test_child_is_a_client_of_the_private_socket_without_access_control() -> None:
    conf = json.loads(child_config(ACL_PROFILE, PRIVATE))
    assert conf["mode"] == "client"
    assert conf["connect"]["endpoints"] == [PRIVATE]
    assert conf["listen"]["endpoints"] == []
    assert conf["access_control"]["enabled"] is False
    assert conf["transport"]["auth"]["usrpwd"]["dictionary_file"] is None


def test_router_keeps_the_profile_and_adds_the_private_endpoint(tmp_path: Path) -> None:
    conf = router_config(ACL_PROFILE, ["tcp/127.0.0.1:7999"], [], PRIVATE)
    assert json.loads(conf.get_json("mode")) == "router"
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7999", PRIVATE]
    assert json.loads(conf.get_json("access_control/enabled")) is True
    assert not requires_credentials(conf)  # no dictionary named in the environment
    users = tmp_path / "users"
    users.write_text("machine:x\n")
    conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users)))
    assert requires_credentials(conf)


@pytest.mark.parametrize(("hang_s", "lease_ms"), [(0.0, 1000), (1.0, 1000), (3.0, 3000)])
def test_both_ends_of_the_childs_link_wait_at_least_the_hang_limit(
    hang_s: float, lease_ms: int
) -> None:
    """The profile's 1 s lease stands unless `--hang` is longer: a daemon frozen for less than
    `--hang` stays on the bus, whichever end of its link would have dropped it."""
    child = json.loads(child_config(ACL_PROFILE, PRIVATE, hang_s))
    router = router_config(ACL_PROFILE, [], [], PRIVATE, hang_s)
    assert child["transport"]["link"]["tx"]["lease"] == lease_ms
    assert json.loads(router.get_json("transport/link/tx/lease")) == lease_ms


def test_the_packaged_picto_config_fits_the_default_io_map(tmp_path: Path) -> None:
    rsc = CONFIG_RSC
    image = tmp_path / "procimg"
    image.write_bytes(bytes(4096))
    findings = check_revpi_io(MachineConfig().hal.iomap, str(rsc), str(image))
    assert [f.category for f in findings] == ["io_shared"]  # the DIO's other outputs: a warning


# ------------------------------------------------------------------------- credentials
def test_credentials_from_files(tmp_path: Path) -> None:
    pwd = tmp_path / "pw"
    pwd.write_text("s3cret\n")
    users = tmp_path / "users"
    users.write_text("rider:s3cret\n")
    env = {
        env_name(MACHINE, "USER"): "machine",
        env_name(MACHINE, "PASSWORD_FILE"): str(pwd),
        env_name(MACHINE, "DICTIONARY_FILE"): str(users),
        env_name(MACHINE, "TLS_CERTIFICATE"): str(pwd),
    }
    out = {k: json.loads(v) for k, v in zenoh_settings(MACHINE, env).items()}
    assert out["transport/auth/usrpwd/user"] == "machine"
    assert out["transport/auth/usrpwd/password"] == "s3cret"
    assert out["transport/auth/usrpwd/dictionary_file"] == str(users.resolve())
    assert out["transport/link/tls/listen_certificate"] == str(pwd.resolve())
    assert zenoh_settings(RIDER, env) == {}  # the other side's variables are not ours


@pytest.mark.parametrize(
    ("env", "complaint"),
    [
        ({"RIDER_ZENOH_USER": "rider"}, "RIDER_ZENOH_PASSWORD_FILE is not set"),
        ({"RIDER_ZENOH_PASSWORD_FILE": "PW"}, "RIDER_ZENOH_USER is not set"),
        ({"RIDER_ZENOH_USER": "a:b", "RIDER_ZENOH_PASSWORD_FILE": "PW"}, "no ':'"),
        ({"RIDER_ZENOH_USER": "r", "RIDER_ZENOH_PASSWORD_FILE": "EMPTY"}, "one non-empty line"),
        ({"RIDER_ZENOH_USER": "r", "RIDER_ZENOH_PASSWORD_FILE": "/nope"}, "cannot read"),
        ({"RIDER_ZENOH_TLS_ROOT_CA": "/nope/ca.crt"}, "RIDER_ZENOH_TLS_ROOT_CA"),
    ],
)
def test_bad_credential_variables_say_which_one(
    tmp_path: Path, env: dict[str, str], complaint: str
) -> None:
    (tmp_path / "pw").write_text("x")
    (tmp_path / "empty").write_text("\n")
    paths = {"PW": str(tmp_path / "pw"), "EMPTY": str(tmp_path / "empty")}
    env = {k: paths.get(v, v) for k, v in env.items()}
    with pytest.raises(CredentialError, match=complaint):
        zenoh_settings(RIDER, env)
