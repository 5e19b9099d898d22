"""The site router: Zenoh's router mode with the machine's own logins and rules.

    python site_router.py --zenoh-config /etc/machine/zenoh.json5 \
        --listen tcp/0.0.0.0:7447 --listen tls/0.0.0.0:7448 [--connect tls/HOST:7448]...

The router is Zenoh's (the eclipse-zenoh library's router mode, the same code as zenohd); this
program only builds its config the way the machine builds its own — the access-controlled
profile (zenoh/acl.json5 or zenoh/tls.json5), its `<login>` rules made per station
(service/bus/stations.py), the secrets from the MACHINE_ZENOH_* files — and holds the session
until SIGTERM. So through the router each login can do exactly what it can at the machine, and
one file says what that is.

Riders log in to the router with their own passwords. A link the router dials has no login (a
Zenoh password proves the dialer to the listener, never the other way), so whatever the router
dials — another host's router — is known by its TLS certificate (subject `router-certificate`
of the profile, its CN `router`, signed by the site's CA); machines dial the router and log in
as `machine`. The router refuses to start where that cannot hold (docs/deploy.md).

Exit codes: 0 stopped by a signal, 2 a config it will not run (the reason on stderr).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import signal
import sys
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

from ride_machine.common.credentials import CredentialError
from ride_machine.common.zenoh_session import open_session
from ride_machine.service.bus.session import close_session, zenoh_config
from ride_machine.service.bus.stations import StationError
from ride_machine.service.logfmt import flush_logs, setup_logging

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("site-router")

CONNECT_ENV = "SITE_ROUTER_CONNECT"
"""Other hosts' routers to dial, besides --connect (spaces or commas between endpoints)."""
EXIT_CONFIG = 2


class RouterConfigError(ValueError):
    """A router config that would not enforce the profile (or could not run)."""


def build(profile: Path, listen: list[str], connect: list[str]) -> zenoh.Config:
    """The router's Zenoh config: `profile` as the machine reads it, in router mode, on these
    endpoints; `RouterConfigError` (or a credential error) when it would not hold."""
    try:
        conf = zenoh_config(profile, listen, connect)
    except (CredentialError, StationError) as exc:
        raise RouterConfigError(str(exc)) from None
    conf.insert_json5("mode", '"router"')
    if not connect:  # zenoh_config keeps the profile's endpoints when given none
        conf.insert_json5("connect/endpoints", "[]")
    check(json.loads(str(conf)))
    return conf


def check(conf: dict[str, Any]) -> None:
    """Refuse a router that would let anything through unchecked, or dial what it cannot tell."""
    acl = conf.get("access_control") or {}
    if not acl.get("enabled") or acl.get("default_permission") != "deny":
        raise RouterConfigError(
            "the profile has no access control that denies by default: the site router runs"
            " zenoh/acl.json5 or zenoh/tls.json5 only"
        )
    usrpwd = conf["transport"]["auth"]["usrpwd"]
    if not usrpwd.get("dictionary_file"):
        raise RouterConfigError("MACHINE_ZENOH_DICTIONARY_FILE is not set: nobody could log in")
    tls = conf["transport"]["link"].get("tls") or {}
    connect = conf["connect"]["endpoints"]
    if isinstance(connect, dict):  # per-mode endpoints
        connect = connect.get("router") or []
    for endpoint in connect:
        if not endpoint.startswith("tls/"):
            raise RouterConfigError(
                f"connect {endpoint}: a router dials tls/ only (what it dials logs in to"
                " nothing, so only a certificate can say that it is a router)"
            )
    if connect and not tls.get("root_ca_certificate"):
        raise RouterConfigError(
            "MACHINE_ZENOH_TLS_ROOT_CA is not set: without the site's CA any certificate"
            " named `router` would pass"
        )
    if connect and not usrpwd.get("user"):
        raise RouterConfigError("MACHINE_ZENOH_USER is not set: the router logs in where it dials")
    listen = conf["listen"]["endpoints"]
    if isinstance(listen, dict):
        listen = listen.get("router") or []
    tls_listen = [e for e in listen if e.startswith("tls/")]
    if tls_listen and not (tls.get("listen_certificate") and tls.get("listen_private_key")):
        raise RouterConfigError(
            f"listen {tls_listen[0]} without MACHINE_ZENOH_TLS_CERTIFICATE and"
            " MACHINE_ZENOH_TLS_PRIVATE_KEY"
        )


def endpoints_from_env(env: Mapping[str, str]) -> list[str]:
    """The endpoints of `SITE_ROUTER_CONNECT`."""
    return [e for e in re.split(r"[\s,]+", env.get(CONNECT_ENV, "")) if e]


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="site-router", description=__doc__.split("\n")[0])
    p.add_argument("--zenoh-config", type=Path, required=True, help="the machine's ACL profile")
    p.add_argument("--listen", action="append", default=[], help="endpoint to listen on")
    p.add_argument("--connect", action="append", default=[], help="another router (tls/…)")
    p.add_argument("--log-level", default="info")
    args = p.parse_args(argv)
    setup_logging(args.log_level)
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    connect = [*args.connect, *endpoints_from_env(os.environ)]
    try:
        conf = build(args.zenoh_config, args.listen, connect)
    except RouterConfigError as exc:
        print(f"site-router: {exc}", file=sys.stderr)
        flush_logs()
        return EXIT_CONFIG
    session = open_session(conf)
    log.info(
        "event=router_ready zid=%s listen=%s connect=%s",
        session.zid(),
        ",".join(args.listen) or "-",
        ",".join(connect) or "-",
    )
    stop.wait()
    closed = close_session(session)
    log.info("event=stopped code=0 closed=%s", str(closed).lower())
    flush_logs()
    return 0


if __name__ == "__main__":
    sys.exit(main())
