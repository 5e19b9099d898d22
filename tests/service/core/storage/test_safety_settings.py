"""Safety settings are not ordinary parameters (issue 43, point 7; service/core/storage/safety.py):
an online write makes one stricter, never less strict than the config file, and nothing less
strict while anything moves."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.params import ParamSet
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.storage.params import SPECS, ParamRegistry
from ride_machine.service.core.storage.persist import PARAMS_FILE, ParamStore
from ride_machine.service.core.storage.safety import CONFIG_ONLY, SAFETY, in_effect, weaker
from ride_machine.service.errors import ParamLocked

LESS_STRICT = {
    "rider_loss.policy": "ignore",
    "rider_loss.grace_s": 5.0,
    "rider_loss.timeout_s": 2.0,
    "tilt.min_deg": -10.0,
    "tilt.max_deg": 80.0,
    "tilt.home_timeout_s": 30.0,
    "tilt.move_timeout_margin_s": 10.0,
    "rotate.revolution_timeout_s": 20.0,
    "rotate.backoff_timeout_s": 5.0,
    "rotate.speed_tolerance": 0.8,
}
STRICTER = {
    "rider_loss.policy": "stop",
    "rider_loss.grace_s": 0.0,
    "rider_loss.timeout_s": 0.4,
    "tilt.min_deg": 5.0,
    "tilt.max_deg": 50.0,
    "tilt.home_timeout_s": 8.0,
    "tilt.move_timeout_margin_s": 1.0,
    "rotate.revolution_timeout_s": 6.0,
    "rotate.backoff_timeout_s": 1.0,
    "rotate.speed_tolerance": 0.3,
}


def req(value: object = None, **kw: object) -> ParamSet:
    return ParamSet.model_validate({"transaction_id": "t", "value": value, **kw})


def registry(tmp_path: Path, config: MachineConfig | None = None) -> ParamRegistry:
    return ParamRegistry(config or MachineConfig(), ParamStore(tmp_path))


@pytest.mark.hazard("H25")
def test_the_tables_cover_every_safety_setting() -> None:
    assert set(LESS_STRICT) == set(STRICTER) == set(SAFETY)
    assert set(SAFETY) <= set(SPECS)
    assert not set(CONFIG_ONLY) & set(SPECS)  # the watchdog and the period: config file only
    for name in SAFETY:
        default = SPECS[name].default(MachineConfig())
        assert weaker(name, LESS_STRICT[name], default), name
        assert not weaker(name, STRICTER[name], default), name


@pytest.mark.hazard("H25", "H29")
@pytest.mark.parametrize("name", sorted(SAFETY))
def test_a_write_less_strict_than_the_config_file_is_refused_standing_still(
    tmp_path: Path, name: str
) -> None:
    reg = registry(tmp_path)
    before = reg.get(name).value
    with pytest.raises(ParamLocked) as err:
        reg.set(name, req(LESS_STRICT[name], persist=True), moving=False, now=1.0)
    assert err.value.to_error().code is ErrorCode.PARAM_LOCKED
    assert "config file" in err.value.message and "stricter" in err.value.message
    assert reg.get(name).value == before
    assert not (tmp_path / PARAMS_FILE).exists()


@pytest.mark.parametrize("name", sorted(SAFETY))
def test_stricter_is_taken_and_back_to_the_file_only_standing_still(
    tmp_path: Path, name: str
) -> None:
    reg = registry(tmp_path, MachineConfig().with_overrides(rider_loss={"grace_s": 2.0}))
    default = reg.get(name).value
    moving = not SPECS[name].locked_while_moving  # a stricter value may come mid-ride
    assert reg.set(name, req(STRICTER[name]), moving=moving, now=1.0).value == STRICTER[name]
    with pytest.raises(ParamLocked, match="while the machine is moving"):
        reg.set(name, req(reset=True), moving=True, now=2.0)
    assert reg.set(name, req(reset=True), moving=False, now=3.0).value == default


def test_a_config_file_may_make_a_setting_less_strict(tmp_path: Path) -> None:
    config = MachineConfig().with_overrides(rider_loss={"policy": "ignore", "timeout_s": 2.0})
    reg = registry(tmp_path, config)
    assert reg.config.rider_loss.policy == "ignore"
    assert reg.set("rider_loss.policy", req("pause"), moving=True, now=1.0).value == "pause"
    assert in_effect(reg.project)["rider_loss.policy"] == "ignore"


@pytest.mark.hazard("H25")
def test_a_persisted_value_less_strict_than_the_config_file_is_ignored(tmp_path: Path) -> None:
    """A params.json written by an older version (or by hand) cannot weaken the file either."""
    doc = {"version": 1, "params": {"rider_loss.policy": {"value": "ignore", "changed_at": 1.0}}}
    (tmp_path / PARAMS_FILE).write_text(json.dumps(doc))
    reg = registry(tmp_path)
    assert reg.get("rider_loss.policy").value == "pause"
    assert any("less strict than the config file" in w for w in reg.warnings), reg.warnings
