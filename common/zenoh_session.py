"""Opening a Zenoh session the way this project does, for the daemon and the Rider alike.

The config: the shared zenoh.json5 (or Zenoh's defaults, made private), the caller's endpoints,
the side's secrets from files its environment names (`common.credentials`), a bound on the
messages it reassembles (`MAX_MESSAGE_BYTES`) and on how long a send waits for a peer that does
not read (`BLOCK_WAIT_US`). Opening it: Zenoh's runtime laid out first where
the caller asks (`common.runtime`), and a layout Zenoh cannot read said as an error that names
it, not a crash. What differs between the two sides is their `Side`.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from ride_machine.schema.codec import MAX_REPLY_BYTES

from .credentials import MACHINE, RIDER, zenoh_settings
from .runtime import first_session_on, unreadable_layout

LOCAL_ENDPOINT = "tcp/127.0.0.1:7447"
"""Where the daemon listens and a Rider connects without a config file or endpoints: this host
only (beyond it, use an authenticated profile)."""


@dataclass(frozen=True)
class Side:
    """How one side sets up its sessions, beyond what both do."""

    credentials: str
    """Whose secrets (`MACHINE` or `RIDER` in `common.credentials`)."""
    without_file: Mapping[str, str] = field(default_factory=dict)
    """Settings (config path → JSON5) without a zenoh.json5."""
    always: Mapping[str, str] = field(default_factory=dict)
    """Settings whatever the file says."""
    default_connect: tuple[str, ...] = ()
    """Connect here when neither the caller nor the file names an endpoint."""


MACHINE_SIDE = Side(
    MACHINE,
    without_file={
        "listen/endpoints": json.dumps([LOCAL_ENDPOINT]),
        # Read-only, as in zenoh.json5: Riders' default-machine lookup reads our summary there.
        "adminspace": "{enabled: true, permissions: {read: true, write: false}}",
    },
)
"""The daemon: it listens (on this host by default)."""

RIDER_SIDE = Side(
    RIDER,
    # A Rider's own admin space stays off: the default-machine lookup reads other nodes' (and
    # zenoh 1.10's token/link-state handlers can wedge a session, rider/discovery.py).
    always={"adminspace/enabled": "false"},
    default_connect=(LOCAL_ENDPOINT,),
)
"""A Rider: it connects out (to this host's daemon by default) and listens only when asked, so
it never takes the daemon's port when both run on one host."""


MAX_MESSAGE_SETTING = "transport/link/rx/max_message_size"
MAX_MESSAGE_BYTES = 2 * MAX_REPLY_BYTES
"""The largest message a session reassembles from fragments; a larger one is dropped (Zenoh
1.x's default, 1 GiB, let one peer make us buffer that much per channel). Twice the largest
reply a Rider reads: every request (64 KiB at most) and reply fits with room, and a payload of
up to 1 MiB still reaches the daemon to be refused by name (`PAYLOAD_TOO_LARGE`)."""


BLOCK_WAIT_SETTING = "transport/link/tx/queue/congestion_control/block/wait_before_close"
BLOCK_WAIT_US = 250_000
"""How long a message that must not be dropped waits for room toward a peer whose queue stays
full before Zenoh closes that link (Zenoh's default: 5 s). Since Zenoh 1.8 a reply takes the
asker's QoS, and a `get` blocks by default: a peer that asks and stops reading (its handler
full, its application stuck) held the daemon's Zenoh thread that long, and with it every other
station's commands and heartbeats (a Stop 4.5 s late; the deadman, 0.5 s by default, lost the
controlling Rider). A quarter of a second is half the deadman's default timeout; a peer that
reads nothing for that long is cut, and a live one reconnects and asks again."""


def _bounded(conf: zenoh.Config, setting: str, value: int) -> None:
    """`setting` set to `value` where the config leaves it at Zenoh's default."""
    if conf.get_json(setting) == zenoh.Config().get_json(setting):
        conf.insert_json5(setting, str(value))


class UnreadableRuntime(ValueError):
    """`ZENOH_RUNTIME` in the environment is a layout Zenoh cannot read (it panics)."""


def file_config(path: Path | None) -> zenoh.Config:
    """The zenoh.json5 at `path` as it is, or Zenoh's defaults without one; where it leaves
    Zenoh's reassembly unbounded (its default), bounded to `MAX_MESSAGE_BYTES`, and where it
    leaves a blocked send waiting Zenoh's 5 s, `BLOCK_WAIT_US`."""
    conf = zenoh.Config.from_file(str(path)) if path is not None else zenoh.Config()
    _bounded(conf, MAX_MESSAGE_SETTING, MAX_MESSAGE_BYTES)
    _bounded(conf, BLOCK_WAIT_SETTING, BLOCK_WAIT_US)
    return conf


def zenoh_config(
    side: Side,
    path: Path | None,
    listen: list[str] | None = None,
    connect: list[str] | None = None,
) -> zenoh.Config:
    """`side`'s session config: the shared zenoh.json5 (or Zenoh's defaults), `listen`
    replacing its listen endpoints (`[]`: none; None keeps them), `connect` its connect
    endpoints (when not empty); `CredentialError` when the side's secrets cannot be used."""
    conf = file_config(path)
    if path is None:
        conf.insert_json5("mode", '"peer"')
        # As zenoh.json5: explicit endpoints only. Zenoh's own default (multicast scouting on)
        # would join any peer on the LAN, and another machine with this id would refuse us.
        conf.insert_json5("scouting/multicast/enabled", "false")
        _insert(conf, side.without_file)
    if listen is not None:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    elif side.default_connect and not json.loads(conf.get_json("connect/endpoints") or "[]"):
        conf.insert_json5("connect/endpoints", json.dumps(list(side.default_connect)))
    # Secrets come from files named in the environment, never from the image or this file.
    _insert(conf, zenoh_settings(side.credentials))
    _insert(conf, side.always)
    return conf


def open_session(conf: zenoh.Config, zenoh_threads: int | None = None) -> zenoh.Session:
    """The session. With `zenoh_threads` (a library: the Rider), the process's first session
    lays out Zenoh's runtime on that many worker threads (`first_session_on`; 0: Zenoh's own);
    None: the process laid it out already (the daemon: `use_runtime`). A `ZENOH_RUNTIME` Zenoh
    cannot read is `UnreadableRuntime`, naming it."""
    layout: contextlib.AbstractContextManager[object] = (
        contextlib.nullcontext() if zenoh_threads is None else first_session_on(zenoh_threads)
    )
    with layout:
        try:
            return zenoh.open(conf)
        except BaseException as exc:
            if (unreadable := unreadable_layout(exc)) is None:
                raise
            raise UnreadableRuntime(unreadable) from None


def _insert(conf: zenoh.Config, settings: Mapping[str, str]) -> None:
    for setting, value in settings.items():
        conf.insert_json5(setting, value)
