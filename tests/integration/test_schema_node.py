"""The JSON Schema, proven from outside Python: Node's ajv validates replies captured from a
live daemon against schema/json/ (skipped, with the reason, where node or npm is missing).

Every key of the key table (schema/keys.py) that answers queries is asked once with JSON, so
the table is also checked against what the daemon really serves.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

from ride_machine.rider.client import Rider
from ride_machine.schema.keys import KEYS, Direction
from tests.integration.support import fast_daemon, prepare
from tests.nodejs import JS, node_module
from tests.procs import REPO

SCHEMA_DIR = REPO / "schema" / "json"

# A valid request body for the keys that need one; other keys are asked with just a
# transaction id (commands refused in the current state still reply, with a failed Reply).
BODIES: dict[str, dict[str, Any]] = {
    "params/<name>": {"value": 1.0},
    "sim/estop": {"pressed": False},
    "sim/home": {"axis": "rotate"},
    "sim/stall": {"axis": "tilt", "stalled": False},
}
CONCRETE = {"params/<name>": "params/tilt.tolerance_deg"}
SKIP_COMMANDS = {"cmd/calibrate/tilt", "cmd/calibrate/rotate", "cmd/home", "cmd/start"}
"""Not sent again here: they would set the machine moving mid-capture."""


def node_ready() -> None:
    """ajv installed from the lock file, and node to run it; or skip saying why."""
    node_module("ajv", node=True)


def ask_json(rider: Rider, key: str, body: dict[str, Any] | None) -> list[Any]:
    selector = f"{rider.base}/{key}?format=json"
    kwargs: dict[str, Any] = {"timeout": 5.0}
    if body is not None:
        kwargs.update(payload=json.dumps(body).encode(), encoding="application/json")
    out = []
    for reply in rider.session.get(selector, **kwargs):
        sample = reply.ok if reply.ok is not None else reply.err
        assert sample is not None
        out.append(json.loads(sample.payload.to_bytes()))
    return out


def capture(rider: Rider) -> list[dict[str, Any]]:
    """One JSON reply (or several, for wildcard reads) from every queryable key."""
    captures: list[dict[str, Any]] = []
    for n, spec in enumerate(KEYS):
        if spec.direction in (Direction.PUBLISH, Direction.LIVELINESS):
            continue
        if spec.key in SKIP_COMMANDS:
            continue
        key = CONCRETE.get(spec.key) or "/".join(
            "*" if part.startswith("<") else part for part in spec.key.split("/")
        )
        body = None
        if spec.request is not None:
            body = {"transaction_id": f"schema-{n}", **BODIES.get(spec.key, {})}
        replies = ask_json(rider, key, body)
        assert replies, f"{key}: no reply (is the key table right?)"
        captures += [{"key": spec.key, "payload": p} for p in replies]
    # Every parameter, as a wildcard read returns them.
    captures += [{"key": "params/<name>", "payload": p} for p in ask_json(rider, "params/*", None)]
    return captures


def run_ajv(captures: list[dict[str, Any]], tmp: Path) -> tuple[int, dict[str, Any]]:
    path = tmp / "captures.json"
    path.write_text(json.dumps(captures))
    done = subprocess.run(
        ["node", str(JS / "validate.mjs"), str(SCHEMA_DIR), str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.stdout, done.stderr
    return done.returncode, json.loads(done.stdout)


def test_ajv_validates_real_replies_against_the_checked_in_schema(tmp_path: Path) -> None:
    node_ready()
    with fast_daemon(tmp_path) as daemon, daemon.rider(timeout=5.0) as rider:
        prepare(rider)  # calibrated and homed: status and axis records carry real positions
        captures = capture(rider)
    code, summary = run_ajv(captures, tmp_path)
    assert code == 0, summary["failures"]
    assert summary["failures"] == []
    checked = summary["checked"]
    for model in ("Status", "Reply", "IoValue", "AxisRecord", "CycleDiag", "ParamValue"):
        assert checked.get(model, 0) >= 1, (model, checked)
    assert checked["IoValue"] >= 8 and checked["AxisRecord"] >= 2

    # The check has teeth: a reply that breaks the contract is caught, with the path.
    status = next(c for c in captures if c["key"] == "status")
    broken = [
        {"key": "status", "payload": {**status["payload"], "state": "FLYING"}},
        {"key": "axis/rotate", "payload": {"axis": "rotate", "pn_status": "settled"}},
    ]
    code, summary = run_ajv(broken, tmp_path)
    assert code == 1
    assert [f["key"] for f in summary["failures"]] == ["status", "axis/rotate"]
    assert any("/state" in e for e in summary["failures"][0]["errors"])
