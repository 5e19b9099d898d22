"""The daemon's Zenoh session: its config (`common.zenoh_session`, with the stations' access
control) and a bounded close; it opens with `common.zenoh_session.open_session`."""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path

import zenoh

from ride_machine.common.zenoh_session import LOCAL_ENDPOINT, MACHINE_SIDE
from ride_machine.common.zenoh_session import zenoh_config as shared_config
from ride_machine.service.threads import NamedThread

from .stations import expand, fill_stations, without_role

log = logging.getLogger(__name__)

Session = zenoh.Session
"""The session type, for modules outside this package (they never import `zenoh` themselves)."""

DEFAULT_LISTEN = LOCAL_ENDPOINT
"""Without --listen or a config file: this host only (beyond it, use an authenticated profile)."""


def zenoh_config(
    path: Path | None, listen: list[str] | None = None, connect: list[str] | None = None
) -> zenoh.Config:
    """The daemon's session config (`common.zenoh_session`: the shared zenoh.json5 or Zenoh's
    defaults, endpoints replaced, secrets), its access control expanded per station."""
    conf = shared_config(MACHINE_SIDE, path, listen or None, connect)
    acl = json.loads(conf.get_json("access_control") or "null")
    if isinstance(acl, dict) and acl.get("enabled"):
        # The station logins, then a rule per station for the Riders' own keys
        # (service/bus/stations.py).
        users = json.loads(conf.get_json("transport/auth/usrpwd/dictionary_file") or "null")
        dictionary = Path(users) if users else None
        acl = fill_stations(acl, dictionary)
        conf.insert_json5("access_control", json.dumps(expand(acl)))
        for user in without_role(acl, dictionary) if dictionary else []:
            log.warning(
                "event=login_without_role user=%s detail=%r",
                user,
                "in the dictionary but in no subject of the profile: it may connect and do"
                " nothing (add a station's login to the `rider` subject's usernames)",
            )
    return conf


def close_session(session: zenoh.Session, timeout: float = 3.0) -> bool:
    """Close off the calling thread with a bound: a lossy link can make close() hang."""
    done = threading.Event()

    def closer() -> None:
        session.close()
        done.set()

    NamedThread(target=closer, name="zenoh-close", daemon=True).start()
    return done.wait(timeout)
