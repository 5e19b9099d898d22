"""Online parameters: set, persist, restart, reset, refusals; and the store behind them."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.params import ParamSet
from ride_machine.service.config.model import MachineConfig, RiderLossPolicy
from ride_machine.service.config.validate import validate_data
from ride_machine.service.core.storage.params import SPECS, ParamRegistry, ParamWrongType
from ride_machine.service.core.storage.persist import PARAMS_FILE, ParamStore
from ride_machine.service.errors import ParamLocked, ParamOutOfRange, StorageFailed, UnknownParam

REQUIRED = {
    "tilt.tolerance_deg",
    "tilt.nominal_speed_dps",
    "tilt.max_deg",
    "tilt.min_deg",
    "rotate.nominal_speed_dps",
    "rotate.revolution_timeout_s",
    "tilt.home_timeout_s",
    "bus.heartbeat_s",
    "rider_loss.policy",
}


def req(value: Any = None, *, persist: bool = False, reset: bool = False) -> ParamSet:
    """A write as the registry gets it. A non-finite number never passes the wire's model
    (tests/schema/test_finite_fields.py); it is built past it here, as a caller inside the
    daemon could, to show the registry refuses it too."""
    if isinstance(value, float) and not math.isfinite(value):
        return ParamSet.model_construct(
            transaction_id="t1", value=value, persist=persist, reset=reset
        )
    return ParamSet(transaction_id="t1", value=value, persist=persist, reset=reset)


def registry(data_dir: Path, config: MachineConfig | None = None) -> ParamRegistry:
    return ParamRegistry(config or MachineConfig(), ParamStore(data_dir))


def stored(data_dir: Path) -> dict[str, Any]:
    doc = json.loads((data_dir / PARAMS_FILE).read_text())
    assert doc["version"] == 1
    params: dict[str, Any] = doc["params"]
    return params


# ---------------------------------------------------------------------------- the list
def test_registry_lists_the_online_parameters_but_not_the_scan_period(tmp_path: Path) -> None:
    names = {p.name for p in registry(tmp_path).list()}
    assert names >= REQUIRED
    assert "loop.period_s" not in names


def test_defaults_are_the_project_values_from_the_config(tmp_path: Path) -> None:
    config, findings = validate_data(
        {"tilt": {"tolerance_deg": 2.5}, "rider_loss": {"policy": "stop"}}
    )
    assert config is not None, findings
    reg = registry(tmp_path, config)
    tol = reg.get("tilt.tolerance_deg")
    assert (tol.value, tol.default, tol.persisted, tol.changed_at) == (2.5, 2.5, False, None)
    assert reg.get("rider_loss.policy").value == "stop"
    assert reg.config == config


def test_records_carry_unit_range_and_lock(tmp_path: Path) -> None:
    reg = registry(tmp_path)
    tol = reg.get("tilt.tolerance_deg")
    assert (tol.unit, tol.minimum, tol.maximum, tol.locked_while_moving) == ("°", 0.0, 10.0, True)
    timeout = reg.get("rotate.revolution_timeout_s")
    assert (timeout.unit, timeout.locked_while_moving) == ("s", False)
    policy = reg.get("rider_loss.policy")
    assert "pause, stop, ignore" in policy.description
    for name in (
        "tilt.nominal_speed_dps",
        "tilt.min_deg",
        "tilt.max_deg",
        "rotate.nominal_speed_dps",
    ):
        assert SPECS[name].locked_while_moving, name
    assert not SPECS["bus.heartbeat_s"].locked_while_moving


# ---------------------------------------------------------------- set / persist / restart
def test_set_without_persist_applies_now_and_is_gone_after_restart(tmp_path: Path) -> None:
    reg = registry(tmp_path)
    got = reg.set("tilt.tolerance_deg", req(2.0), moving=False, now=100.0)
    assert (got.value, got.default, got.persisted, got.changed_at) == (2.0, 1.0, False, 100.0)
    assert reg.config.tilt.tolerance_deg == 2.0
    assert reg.live.current.tilt.tolerance_deg == 1.0  # the machine takes it between cycles
    reg.live.take()
    assert reg.live.current.tilt.tolerance_deg == 2.0
    assert reg.project.tilt.tolerance_deg == 1.0
    assert not (tmp_path / PARAMS_FILE).exists()
    again = registry(tmp_path)
    assert again.get("tilt.tolerance_deg").value == 1.0
    assert again.config.tilt.tolerance_deg == 1.0


def test_persisted_value_survives_a_restart(tmp_path: Path) -> None:
    reg = registry(tmp_path)
    got = reg.set("rotate.revolution_timeout_s", req(6.5, persist=True), moving=False, now=7.0)
    assert got.persisted and got.value == 6.5
    assert stored(tmp_path) == {"rotate.revolution_timeout_s": {"value": 6.5, "changed_at": 7.0}}
    again = registry(tmp_path)
    back = again.get("rotate.revolution_timeout_s")
    assert (back.value, back.default, back.persisted, back.changed_at) == (6.5, 8.0, True, 7.0)
    assert again.config.rotate.revolution_timeout_s == 6.5
    assert again.warnings == []


def test_enum_parameter_persists_as_its_string(tmp_path: Path) -> None:
    registry(tmp_path).set("rider_loss.policy", req("stop", persist=True), moving=False, now=1.0)
    again = registry(tmp_path)
    assert again.get("rider_loss.policy").value == "stop"
    assert again.config.rider_loss.policy is RiderLossPolicy.STOP


def test_temporary_write_over_a_persisted_value_is_not_persisted(tmp_path: Path) -> None:
    reg = registry(tmp_path)
    reg.set("bus.heartbeat_s", req(2.0, persist=True), moving=False, now=1.0)
    got = reg.set("bus.heartbeat_s", req(3.0), moving=False, now=2.0)
    assert (got.value, got.persisted) == (3.0, False)
    assert stored(tmp_path)["bus.heartbeat_s"]["value"] == 2.0
    assert registry(tmp_path).get("bus.heartbeat_s").value == 2.0


def test_integer_is_accepted_for_a_float_parameter(tmp_path: Path) -> None:
    got = registry(tmp_path).set("tilt.max_deg", req(50, persist=True), moving=False, now=1.0)
    assert got.value == 50.0 and isinstance(got.value, float)
    assert isinstance(stored(tmp_path)["tilt.max_deg"]["value"], float)


def test_persisting_several_keeps_them_all(tmp_path: Path) -> None:
    reg = registry(tmp_path)
    reg.set("tilt.max_deg", req(50.0, persist=True), moving=False, now=1.0)
    reg.set("tilt.min_deg", req(5.0, persist=True), moving=False, now=2.0)
    again = registry(tmp_path)
    assert (again.config.tilt.min_deg, again.config.tilt.max_deg) == (5.0, 50.0)


# ------------------------------------------------------------------------------ reset
def test_reset_returns_to_default_and_removes_it_from_the_file(tmp_path: Path) -> None:
    reg = registry(tmp_path)
    reg.set("tilt.home_timeout_s", req(8.0, persist=True), moving=False, now=1.0)
    reg.set("bus.heartbeat_s", req(2.0, persist=True), moving=False, now=1.0)
    got = reg.set("tilt.home_timeout_s", req(reset=True), moving=False, now=2.0)
    assert (got.value, got.persisted, got.changed_at) == (10.0, False, None)
    assert reg.config.tilt.home_timeout_s == 10.0
    assert set(stored(tmp_path)) == {"bus.heartbeat_s"}
    again = registry(tmp_path)
    assert again.get("tilt.home_timeout_s").value == 10.0
    assert again.get("bus.heartbeat_s").value == 2.0


def test_reset_of_a_temporary_value_leaves_the_file_alone(tmp_path: Path) -> None:
    reg = registry(tmp_path)
    reg.set("tilt.tolerance_deg", req(3.0), moving=False, now=1.0)
    assert reg.set("tilt.tolerance_deg", req(reset=True), moving=False, now=2.0).value == 1.0
    assert not (tmp_path / PARAMS_FILE).exists()


# ------------------------------------------------------------------------- refusals
@pytest.mark.hazard("H25")
@pytest.mark.parametrize(
    "name",
    ["tilt.tolerance_deg", "tilt.nominal_speed_dps", "tilt.max_deg", "rotate.nominal_speed_dps"],
)
def test_locked_parameter_is_refused_while_moving(tmp_path: Path, name: str) -> None:
    reg = registry(tmp_path)
    value = reg.get(name).value
    assert isinstance(value, float)
    with pytest.raises(ParamLocked) as err:
        reg.set(name, req(value * 0.9, persist=True), moving=True, now=1.0)
    assert err.value.path == "/value"
    assert "moving" in err.value.message and name in err.value.message
    assert err.value.to_error().code is ErrorCode.PARAM_LOCKED
    assert reg.get(name).value == value
    assert reg.config == MachineConfig()
    assert not (tmp_path / PARAMS_FILE).exists()
    # Once the machine stands still the same write goes through.
    assert reg.set(name, req(value * 0.9), moving=False, now=2.0).value == value * 0.9


@pytest.mark.hazard("H25")
def test_reset_of_a_locked_parameter_is_refused_while_moving(tmp_path: Path) -> None:
    reg = registry(tmp_path)
    reg.set("tilt.tolerance_deg", req(2.0), moving=False, now=1.0)
    with pytest.raises(ParamLocked):
        reg.set("tilt.tolerance_deg", req(reset=True), moving=True, now=2.0)
    assert reg.get("tilt.tolerance_deg").value == 2.0


def test_unlocked_parameter_may_change_while_moving(tmp_path: Path) -> None:
    reg = registry(tmp_path)
    assert reg.set("tilt.home_timeout_s", req(8.0), moving=True, now=1.0).value == 8.0
    assert reg.set("rider_loss.policy", req("stop"), moving=True, now=1.0).value == "stop"


def test_unknown_parameter_is_refused(tmp_path: Path) -> None:
    reg = registry(tmp_path)
    with pytest.raises(UnknownParam) as err:
        reg.get("tilt.speed")
    assert "tilt.speed" in err.value.message and "tilt.nominal_speed_dps" in err.value.message
    assert err.value.to_error().code is ErrorCode.UNKNOWN_PARAM
    with pytest.raises(UnknownParam):
        reg.set("loop.period_s", req(0.005), moving=False, now=1.0)
    assert reg.config == MachineConfig()


@pytest.mark.parametrize(
    ("name", "value", "expects"),
    [
        ("tilt.tolerance_deg", "2", "a number"),
        ("tilt.tolerance_deg", True, "a number"),
        ("rider_loss.policy", 1, "one of pause, stop, ignore"),
        ("bus.heartbeat_s", None, "give a value"),
    ],
)
def test_wrong_type_is_refused(tmp_path: Path, name: str, value: Any, expects: str) -> None:
    reg = registry(tmp_path)
    with pytest.raises(ParamWrongType) as err:
        reg.set(name, req(value), moving=False, now=1.0)
    assert err.value.path == "/value"
    assert expects in err.value.message
    assert err.value.to_error().code is ErrorCode.BAD_PAYLOAD
    reg.live.take()
    assert reg.config == reg.live.current == MachineConfig()


def test_reset_with_a_value_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ParamWrongType, match="reset takes no value"):
        registry(tmp_path).set("bus.heartbeat_s", req(2.0, reset=True), moving=False, now=1.0)


@pytest.mark.hazard("H25")
@pytest.mark.parametrize(
    ("name", "value", "says"),
    [
        ("tilt.tolerance_deg", 10.5, "must be > 0 and ≤ 10 °; got 10.5"),
        ("tilt.tolerance_deg", 0, "must be > 0"),
        ("tilt.tolerance_deg", -1.0, "must be > 0"),
        ("tilt.tolerance_deg", math.nan, "got nan"),
        ("bus.heartbeat_s", math.inf, "got inf"),
        ("rotate.speed_tolerance", 1.0, "< 1"),
        ("rider_loss.policy", "halt", "one of pause, stop, ignore; got 'halt'"),
        # FastData user registers: int32 and any finite double (an int past the bounds once
        # crashed the message text and left the query unanswered)
        ("fastdata.int.0", 2**31, "must be ≥ -2147483648 and ≤ 2147483647; got 2147483648"),
        ("fastdata.int.7", -(2**31) - 1, "got -2147483649"),
        ("fastdata.int.0", 10**400, "got an integer of"),
        ("fastdata.double.0", math.inf, "must be a finite number; got inf"),
        ("fastdata.double.3", math.nan, "must be a finite number; got nan"),
        # A JSON integer of 310 digits no float can hold (it left the query unanswered).
        ("rider_loss.timeout_s", 10**310, "must be > 0 and ≤ 60 s; got an integer of"),
        ("fastdata.double.0", -(10**310), "must be a finite number; got an integer of"),
        # Cross-field: a valid number that breaks what the config check guarantees.
        ("rotate.nominal_speed_dps", 30.0, "/rotate/revolution_timeout_s"),
        ("tilt.max_deg", 10.0, "/tilt/calibration_stroke_s"),
        ("tilt.min_deg", 70.0, "must be below tilt.max_deg"),
        ("rotate.revolution_timeout_s", 3.0, "shorter than one revolution"),
        ("tilt.home_timeout_s", 1.0, "shorter than the full tilt travel"),
    ],
)
def test_out_of_range_is_refused(tmp_path: Path, name: str, value: Any, says: str) -> None:
    reg = registry(tmp_path)
    with pytest.raises(ParamOutOfRange) as err:
        reg.set(name, req(value, persist=True), moving=False, now=1.0)
    assert says in err.value.message
    assert err.value.path == "/value"
    assert err.value.to_error().code is ErrorCode.PARAM_OUT_OF_RANGE
    assert reg.config == MachineConfig()
    assert not (tmp_path / PARAMS_FILE).exists()


@pytest.mark.hazard("H25")
def test_live_config_never_has_a_validation_error(tmp_path: Path) -> None:
    # Slower rotation is allowed where the timeout allows for it (a longer timeout is the
    # config file's to give: service/core/storage/safety.py).
    reg = registry(tmp_path, MachineConfig().with_overrides(rotate={"revolution_timeout_s": 20}))
    reg.set("rotate.nominal_speed_dps", req(30.0), moving=False, now=2.0)
    _, findings = validate_data(reg.config.model_dump(mode="json", by_alias=True))
    assert findings.ok, findings


def test_write_that_cannot_be_stored_changes_nothing(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    reg = registry(blocker / "data")  # the data directory cannot be created under a file
    with pytest.raises(StorageFailed) as err:
        reg.set("tilt.tolerance_deg", req(2.0, persist=True), moving=False, now=1.0)
    assert err.value.path == "/persist"
    assert reg.get("tilt.tolerance_deg").value == 1.0
    reg.live.take()
    assert reg.live.current == MachineConfig()
    # Without persist nothing touches the disk, so the write works.
    assert reg.set("tilt.tolerance_deg", req(2.0), moving=False, now=1.0).value == 2.0


# ------------------------------------------------------------ loading persisted values
def write_params(data_dir: Path, params: dict[str, Any]) -> None:
    (data_dir / PARAMS_FILE).write_text(json.dumps({"version": 1, "params": params}))


def test_persisted_value_now_out_of_range_gives_warning_and_default(tmp_path: Path) -> None:
    write_params(
        tmp_path,
        {
            "tilt.tolerance_deg": {"value": 50.0, "changed_at": 1.0},
            "bus.heartbeat_s": {"value": 2.0, "changed_at": 1.0},
        },
    )
    reg = registry(tmp_path)
    [warning] = reg.warnings
    assert "tilt.tolerance_deg=50.0 ignored" in warning and "default 1.0" in warning
    assert reg.get("tilt.tolerance_deg").value == 1.0
    assert reg.get("bus.heartbeat_s").value == 2.0  # the good entry still applies
    assert reg.config.tilt.tolerance_deg == 1.0


def test_persisted_value_that_conflicts_with_a_new_project_config_is_ignored(
    tmp_path: Path,
) -> None:
    # Stored when the rotate speed was high; the project now turns slower.
    write_params(tmp_path, {"rotate.revolution_timeout_s": {"value": 4.0, "changed_at": 1.0}})
    config = MachineConfig().with_overrides(
        rotate={"nominal_speed_dps": 60.0, "revolution_timeout_s": 12.0}
    )
    reg = registry(tmp_path, config)
    [warning] = reg.warnings
    assert "rotate.revolution_timeout_s=4.0 ignored" in warning
    assert reg.config.rotate.revolution_timeout_s == 12.0


@pytest.mark.hazard("H40")
@pytest.mark.parametrize(
    ("entry", "says"),
    [
        ({"no.such": {"value": 1.0}}, "not an online parameter"),
        ({"bus.heartbeat_s": {"value": "fast"}}, "expects a number"),
        ({"bus.heartbeat_s": {"value": [1]}}, "ignored"),
        ({"bus.heartbeat_s": 2.0}, "ignored"),
    ],
)
def test_bad_persisted_entry_is_a_warning(tmp_path: Path, entry: dict[str, Any], says: str) -> None:
    write_params(tmp_path, entry)
    reg = registry(tmp_path)
    [warning] = reg.warnings
    assert says in warning
    assert reg.config == MachineConfig()


def test_an_online_write_the_file_check_warns_about_at_its_own_path_is_refused(
    tmp_path: Path,
) -> None:
    """`bus.heartbeat_s` 1e-9 is only a warning in a file; online nobody would read it."""
    reg = registry(tmp_path)
    with pytest.raises(ParamOutOfRange, match="cannot be held"):
        reg.set("bus.heartbeat_s", req(1e-9), moving=False, now=1.0)
    assert reg.get("bus.heartbeat_s").value == 1.0
