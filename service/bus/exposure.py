"""Is this session reachable beyond this host without a login? (a warning at start-up)."""

from __future__ import annotations

import ipaddress
import json
import logging

import zenoh

LOCAL_ONLY_PROTOCOLS = ("unixsock-stream", "unixpipe", "vsock")
"""Endpoints no other host can dial, whatever their address says."""

HOW_TO_AUTH = (
    "anyone who reaches these endpoints can command the machine; turn authentication on with"
    " --zenoh-config zenoh/acl.json5 (or zenoh/tls.json5) and MACHINE_ZENOH_DICTIONARY_FILE"
    " (`machine credentials init DIR` makes the files), see docs/security.md"
)


def is_loopback(endpoint: str) -> bool:
    """True for `tcp/127.0.0.1:7447`, `udp/[::1]:7447`, `tcp/localhost:7447`, unix sockets."""
    protocol, _, rest = endpoint.partition("/")
    if protocol in LOCAL_ONLY_PROTOCOLS:
        return True
    address = rest.split("#", 1)[0].split("?", 1)[0]
    host = address.rsplit(":", 1)[0] if ":" in address else address
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may resolve to anything
        return False


def authenticated(conf: zenoh.Config) -> bool:
    """True when whoever connects must log in (a user/password dictionary, or mutual TLS)."""
    dictionary = json.loads(conf.get_json("transport/auth/usrpwd/dictionary_file") or "null")
    mtls = json.loads(conf.get_json("transport/link/tls/enable_mtls") or "false")
    return dictionary is not None or mtls is True


def unauthenticated_exposure(conf: zenoh.Config) -> list[str]:
    """The listen endpoints other hosts may reach with no login (empty when none)."""
    if authenticated(conf):
        return []
    endpoints = json.loads(conf.get_json("listen/endpoints") or "[]")
    if isinstance(endpoints, dict):  # per-mode form: {router: [...], peer: [...], client: [...]}
        mode = json.loads(conf.get_json("mode") or '"peer"') or "peer"
        endpoints = endpoints.get(mode, [])
    return [str(e) for e in endpoints if not is_loopback(str(e))]


def warn_if_exposed(conf: zenoh.Config, log: logging.Logger) -> list[str]:
    """One warning at start when other hosts may command the machine with no login."""
    exposed = unauthenticated_exposure(conf)
    if exposed:
        log.warning(
            "event=listen_unauthenticated endpoints=%s detail=%r", ",".join(exposed), HOW_TO_AUTH
        )
    return exposed
