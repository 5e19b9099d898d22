"""Opening and closing the Zenoh session: its config from zenoh.json5, endpoints, secrets."""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path

import zenoh

from schema.credentials import MACHINE, zenoh_settings
from schema.runtime import unreadable_layout
from service.bus.stations import expand, without_role
from service.threads import NamedThread

log = logging.getLogger(__name__)

Session = zenoh.Session
"""The session type, for modules outside this package (they never import `zenoh` themselves)."""

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
"""Without --listen or a config file: this host only (beyond it, use an authenticated profile)."""


def file_config(path: Path | None) -> zenoh.Config:
    """The zenoh.json5 at `path` as it is, or Zenoh's defaults without one."""
    return zenoh.Config.from_file(str(path)) if path is not None else zenoh.Config()


def zenoh_config(
    path: Path | None, listen: list[str] | None = None, connect: list[str] | None = None
) -> zenoh.Config:
    """The session config: the shared zenoh.json5 (or Zenoh's defaults), endpoints replaced."""
    conf = file_config(path)
    if path is None:
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("listen/endpoints", json.dumps([DEFAULT_LISTEN]))
        # As zenoh.json5: explicit endpoints only. Zenoh's own default (multicast scouting on)
        # would join any peer on the LAN, and another machine with this id would refuse us.
        conf.insert_json5("scouting/multicast/enabled", "false")
        # Read-only, as in zenoh.json5: Riders' default-machine lookup reads our summary there.
        conf.insert_json5("adminspace", "{enabled: true, permissions: {read: true, write: false}}")
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    # Secrets come from files named in the environment, never from the image or this file.
    for setting, value in zenoh_settings(MACHINE).items():
        conf.insert_json5(setting, value)
    acl = json.loads(conf.get_json("access_control") or "null")
    if isinstance(acl, dict) and acl.get("enabled"):
        # A rule per station login for the Riders' own keys (service/bus/stations.py).
        conf.insert_json5("access_control", json.dumps(expand(acl)))
        users = json.loads(conf.get_json("transport/auth/usrpwd/dictionary_file") or "null")
        for user in without_role(acl, Path(users)) if users else []:
            log.warning(
                "event=login_without_role user=%s detail=%r",
                user,
                "in the dictionary but in no subject of the profile: it may connect and do"
                " nothing (add a station's login to the `rider` subject's usernames)",
            )
    return conf


def open_session(conf: zenoh.Config) -> zenoh.Session:
    """The session; a `ZENOH_RUNTIME` Zenoh cannot read (it panics) is a `ValueError` that
    names it, not a crash."""
    try:
        return zenoh.open(conf)
    except BaseException as exc:
        if (unreadable := unreadable_layout(exc)) is None:
            raise
        raise ValueError(unreadable) from None


def close_session(session: zenoh.Session, timeout: float = 3.0) -> bool:
    """Close off the calling thread with a bound: a lossy link can make close() hang."""
    done = threading.Event()

    def closer() -> None:
        session.close()
        done.set()

    NamedThread(target=closer, name="zenoh-close", daemon=True).start()
    return done.wait(timeout)
