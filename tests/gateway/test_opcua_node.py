"""An OPC UA client from another stack and language: node-opcua (npm, pinned by
tests/gateway/js/package-lock.json) browses, reads, subscribes and calls through the gateway
(skipped, with the reason, where node or npm is missing)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from tests.gateway.support import Credentials, GatewayProc
from tests.nodejs import node_module

pytestmark = pytest.mark.integration
JS = Path(__file__).resolve().parent / "js"


def test_node_opcua_browses_reads_subscribes_and_calls(
    gateway: GatewayProc, creds: Credentials, tmp_path: Path
) -> None:
    node_module("node-opcua-client", JS, node=True)
    done = subprocess.run(
        ["node", "opcua_check.mjs", gateway.url, "operator", creds.password, "m1"],
        cwd=JS,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        # node-opcua makes its client certificate under the config home: the test's own.
        env={**os.environ, "XDG_CONFIG_HOME": str(tmp_path), "HOME": str(tmp_path)},
    )
    assert done.returncode == 0, done.stderr[-2000:]
    # node-opcua writes its own notices to stdout too: the script's line is the JSON one.
    line = next(x for x in reversed(done.stdout.splitlines()) if x.startswith('{"'))
    seen = json.loads(line)
    assert seen["browse"] == "Good" and seen["stateNode"] == f"ns={seen['namespace']};s=m1/State"
    assert seen["read"]["status"] == "Good" and seen["read"]["value"]
    assert seen["stop"]["good"] and seen["stop"]["outputs"][0] == "RESP_DONE"
    assert seen["home"]["good"] and seen["home"]["outputs"][0] == "RESP_HOME_ACCEPTED"
    assert seen["changes"][-1] == "HOMING"  # the subscription delivered the change
    start = seen["start"]
    assert start["status"] == "BadInvalidState" and not start["good"]
    assert start["outputs"][0] == "WRONG_STATE" and "Start is not accepted" in start["outputs"][1]
    assert seen["stopAgain"]["good"]
