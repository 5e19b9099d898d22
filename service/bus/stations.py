"""One login per operator station: an ACL rule per login, made from the profile's template.

Zenoh's access control matches key expressions and user names, but cannot tie a key to the
login that sends it. The profiles (zenoh/acl.json5, zenoh/tls.json5) therefore write the
Riders' own keys once, as a template with the chunk `<login>` (`rider/<login>/*/heartbeat`),
and the daemon makes one rule per user name of the subjects that use it, as it builds its
session config: login `bay1` may declare and put `rider/bay1/*/alive|heartbeat` only. A login
can thus neither hold nor feed another login's token or heartbeat (docs/security.md).

Left as it is (no daemon to expand it, e.g. under `zenohd`), the template matches no real key:
nobody may supervise, which fails safe (a ride pauses when its Rider's heartbeat is not seen).

The shipped profiles name no station either: their `rider` subject's user name `<stations>`
stands for every login of the dictionary that no other subject names (`fill_stations`), so
the logins `machine credentials init --stations bay1,bay2` makes are stations as they are. The
one login all stations once shared, `rider`, is made only on request (`--shared-rider`), and
the daemon warns at start while it is a station (two stations on one login can hold each
other's Rider keys).
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path
from typing import Any

from ride_machine.schema.rider import login_ok
from ride_machine.service.adapters.credentials import ROLES, SHARED

log = logging.getLogger(__name__)

LOGIN = "<login>"
"""The key chunk a rule's key expressions name the sending login by."""
STATIONS = "<stations>"
"""A subject's user name standing for every dictionary login no other subject names."""


class StationError(ValueError):
    """A profile whose login template cannot be made into rules (a user name that is no key)."""


def expand(acl: dict[str, Any]) -> dict[str, Any]:
    """The `access_control` block with each `<login>` rule made once per user name of each
    subject whose policy uses it (a subject and a policy of its own, `<id>@<login>`); the
    block as it is when no rule has the template."""
    rules = {rule["id"]: rule for rule in acl.get("rules", [])}
    templates = {rid for rid, rule in rules.items() if _is_template(rule)}
    if not templates:
        return acl
    out = copy.deepcopy(acl)
    out["rules"] = [r for r in out.get("rules", []) if r["id"] not in templates]
    subjects = {s["id"]: s for s in acl.get("subjects", [])}
    policies: list[dict[str, Any]] = []
    for policy in out.get("policies", []):
        own = [rid for rid in policy["rules"] if rid in templates]
        policy["rules"] = [rid for rid in policy["rules"] if rid not in templates]
        policies.append(policy)
        for sid in policy["subjects"] if own else []:
            for login in _logins(subjects[sid]):
                per = f"@{login}"
                out["subjects"].append({**subjects[sid], "id": sid + per, "usernames": [login]})
                out["rules"] += [_instance(rules[rid], login) for rid in own]
                policies.append(
                    {
                        "id": f"{policy.get('id', sid)}{per}",
                        "rules": [rid + per for rid in own],
                        "subjects": [sid + per],
                    }
                )
    out["policies"] = [p for p in policies if p["rules"]]
    logins = sorted(s["usernames"][0] for s in out["subjects"] if "@" in s["id"])
    log.info("event=acl_stations logins=%s", ",".join(logins) or "-")
    return out


def fill_stations(acl: dict[str, Any], dictionary: Path | None) -> dict[str, Any]:
    """The block with `<stations>` replaced by the logins of `dictionary` that no other subject
    names and no role has (sorted); as it is when no subject uses it. With no such login the
    placeholder stays (a subject without user names would match every login): no station, and
    a warning."""
    holders = [s for s in acl.get("subjects", []) if STATIONS in (s.get("usernames") or [])]
    if not holders:
        return acl
    users = dictionary_users(dictionary) if dictionary else set()
    if STATIONS in users:
        raise StationError(f"{dictionary}: a login may not be named {STATIONS!r}")
    named = {u for s in acl["subjects"] for u in s.get("usernames") or [] if u != STATIONS}
    # The role logins (machine, monitor, router) are never stations, named or not.
    stations = sorted(u for u in users - named - set(ROLES) if login_ok(u))
    if not stations:
        log.warning(
            "event=no_stations detail=%r",
            f"no login in the dictionary for the {STATIONS} subject: no Rider may command"
            " (machine credentials init DIR --stations NAME,…)",
        )
        return acl
    out = copy.deepcopy(acl)
    for subject in out["subjects"]:
        names = subject.get("usernames") or []
        if STATIONS in names:
            subject["usernames"] = [u for u in names if u != STATIONS] + stations
    if SHARED in stations:
        log.warning(
            "event=shared_login login=%s detail=%r",
            SHARED,
            "one login for every operator station: a station on it can keep another's Rider"
            " alive after that station died, and confirm for it (docs/security.md); give each"
            " station its own: machine credentials init DIR --stations bay1,bay2",
        )
    return out


def without_role(acl: dict[str, Any], dictionary: Path) -> list[str]:
    """The logins of `dictionary` (`user:password` lines) that no subject names: they can open a
    session and nothing else (a station whose login was made but not listed, usually)."""
    named = {u for s in acl.get("subjects", []) for u in s.get("usernames") or []}
    return sorted(dictionary_users(dictionary) - named)


def dictionary_users(dictionary: Path) -> set[str]:
    """The user names of a Zenoh dictionary file (`user:password` lines); none when it cannot be
    read (Zenoh itself says what is wrong with the file)."""
    try:
        lines = dictionary.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError):
        return set()
    return {line.split(":", 1)[0].strip() for line in lines if ":" in line}


def _is_template(rule: dict[str, Any]) -> bool:
    return any(LOGIN in key.split("/") for key in rule.get("key_exprs", []))


def _logins(subject: dict[str, Any]) -> list[str]:
    names = [n for n in subject.get("usernames", []) if n != STATIONS]  # none: fill_stations
    if not names:
        log.warning(
            "event=acl_template_unused subject=%s detail=%r",
            subject["id"],
            "no user names: nobody in it may supervise (rider/<login>/… needs a login)",
        )
    for name in names:
        if not login_ok(name):
            raise StationError(
                f"access_control subject {subject['id']!r}: user name {name!r} cannot name keys"
                " (rider/<login>/…): letters, digits and ._@+- only, at most 64"
            )
    return names


def _instance(rule: dict[str, Any], login: str) -> dict[str, Any]:
    keys = ["/".join(login if c == LOGIN else c for c in k.split("/")) for k in rule["key_exprs"]]
    return {**rule, "id": f"{rule['id']}@{login}", "key_exprs": keys}
