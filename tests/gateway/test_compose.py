"""docker/compose.gateway.yaml's gateway service: opt in (a file of its own, added to
compose.yaml with `-f`: Debian's podman-compose ignores profiles), a command the gateway's own
parser takes, ports on host loopback, the `rider` login and the files `machine credentials init`
makes."""

from __future__ import annotations

from pathlib import Path

from ride_machine.service.adapters.credentials import password_file
from ride_machine.service.adapters.opcua_credentials import CERTIFICATE, PRIVATE_KEY, USERS
from tests.deploy import spec
from tests.procs import REPO

GATEWAY_OVERRIDE = REPO / "docker" / "compose.gateway.yaml"


def test_the_gateway_service_is_opt_in_and_on_host_loopback() -> None:
    compose = spec.load_compose()
    assert "gateway" not in compose["services"]  # not started by a plain `up`
    override = spec.load_compose(GATEWAY_OVERRIDE)
    svc = spec.service(override, "gateway")
    assert "profiles" not in svc
    # its own image, the Dockerfile's `gateway` target: the machine's carries no OPC UA stack
    name, tag = spec.service(compose, "machine")["image"].split(":")
    assert svc["image"] == f"{name}-gateway:{tag}"
    assert svc["build"] == {"context": ".", "target": "gateway"}
    args = spec.parse_cli(spec.command(svc))
    assert args.cmd == "gateway"
    gw = args.gateway
    assert svc["ports"] == [
        f"127.0.0.1:{gw.opcua[1]}:{gw.opcua[1]}",
        f"127.0.0.1:{gw.metrics[1]}:{gw.metrics[1]}",
    ]
    env = spec.environment(svc)
    assert env["RIDER_ZENOH_USER"] == "gateway" and not gw.monitor  # a station of its own
    secrets = spec.secret_paths(override, svc, REPO / "secrets")
    assert secrets[env["RIDER_ZENOH_PASSWORD_FILE"]] == password_file(REPO / "secrets", "gateway")
    made = {Path(name) for name in (USERS, CERTIFICATE, PRIVATE_KEY)}
    assert {
        secrets[str(p)].relative_to(REPO / "secrets")
        for p in (gw.users, gw.certificate, gw.private_key)
    } == made
    (endpoint,) = args.connect
    assert endpoint == spec.environment(spec.service(compose, "rider"))["RIDER_CONNECT"]
