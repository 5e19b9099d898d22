"""Calibration on the bus through real Zenoh: read with `rider calibration` and a raw query,
entered by hand with `rider calibration set` (validated, refused while moving, published,
persisted as manual across a restart)."""

from __future__ import annotations

import json
import queue
import subprocess
from pathlib import Path

import pytest
import zenoh

from ride_machine.schema.calibration import CalibrationRecord, CalibrationSource
from ride_machine.schema.codec import Format, decode
from ride_machine.schema.status import MachineState, Status
from tests.integration.support import fast_args
from tests.procs import Daemon, running_daemon

pytestmark = pytest.mark.integration

CLI_TIMEOUT_S = 30.0
# The fast config: 720°/s nominal, so one revolution is 0.5 s (± the 10 % tolerance).
MANUAL = ["--tilt-offset", "1194", "--tilt-gain", "40", "--rotate-revolution-s", "0.5"]
MANUAL += ["--rotate-home-arc", "30"]


def rider(daemon: Daemon, *args: str) -> subprocess.CompletedProcess[str]:
    return daemon.run_rider(*args, timeout=CLI_TIMEOUT_S)


def session_for(daemon: Daemon) -> zenoh.Session:
    conf = zenoh.Config.from_file(str(daemon.zenoh_config))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps([daemon.endpoint]))
    return zenoh.open(conf)


def test_calibration_is_read_entered_refused_published_and_persisted(tmp_path: Path) -> None:
    with running_daemon(tmp_path, extra=fast_args(tmp_path)) as daemon:
        empty = CalibrationRecord.model_validate_json(rider(daemon, "--json", "calibration").stdout)
        assert empty.tilt is None and empty.rotate is None and not empty.complete

        raw = session_for(daemon)
        published: queue.Queue[CalibrationRecord] = queue.Queue()
        sub = raw.declare_subscriber(
            "machine/m1/calibration",
            lambda s: published.put(
                decode(CalibrationRecord, s.payload.to_bytes(), Format.MSGPACK)
            ),
        )
        try:
            done = rider(daemon, "--json", "calibration", "set", *MANUAL)
            assert done.returncode == 0, done.stderr
            entered = CalibrationRecord.model_validate_json(done.stdout)
            assert entered.complete and entered.tilt is not None and entered.rotate is not None
            assert entered.tilt.source is entered.rotate.source is CalibrationSource.MANUAL
            assert entered.rotate.speed_dps == pytest.approx(720.0)
            assert published.get(timeout=5.0).tilt == entered.tilt
            # A plain Zenoh query, JSON as a foreign client would ask.
            replies = list(raw.get("machine/m1/calibration?format=json", timeout=5.0))
            assert replies and replies[0].ok is not None
            read = json.loads(replies[0].ok.payload.to_bytes())
            assert read["tilt"]["source"] == "manual" and read["tilt"]["gain_counts_per_deg"] == 40
        finally:
            sub.undeclare()
            raw.close()

        implausible = rider(daemon, "calibration", "set", "--tilt-offset", "1", "--tilt-gain", "3")
        assert implausible.returncode == 1 and "PARAM_OUT_OF_RANGE" in implausible.stderr
        unusable = rider(daemon, "calibration", "set", "--tilt-offset", "1", "--tilt-gain", "-3")
        assert unusable.returncode == 2  # refused before sending
        with daemon.rider() as r:
            # A Home held by the E-stop (the rotate stalled so it cannot finish first) is a
            # motion under way: values cannot be entered until it is stopped.
            r.sim("stall", axis="rotate", stalled=True)
            r.home()
            r.sim("estop", pressed=True)
            moving = rider(daemon, "calibration", "set", *MANUAL)
            assert moving.returncode == 1 and "WRONG_STATE" in moving.stderr, moving.stderr
            r.sim("estop", pressed=False)
            r.sim("clear")
            for update in r.watch(("status",), timeout=5.0):  # the release is seen next cycle
                if isinstance(update, Status) and not update.estop.active:
                    break
            assert r.stop().state is MachineState.DONE

    with running_daemon(tmp_path, extra=fast_args(tmp_path)) as again:
        shown = rider(again, "calibration")
        assert shown.returncode == 0 and shown.stdout.count("manual") == 2, shown.stdout
        after = CalibrationRecord.model_validate_json(rider(again, "--json", "calibration").stdout)
        assert after.tilt == entered.tilt and after.rotate == entered.rotate
