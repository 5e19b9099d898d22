"""Safety settings: the online parameters that keep a ride safe, which a `rider` login may only
make stricter. Pure rules: the parameter registry (service/core/storage/params.py) applies them.

The deadman (`rider_loss.*`), the tilt's travel limits and the sensor timeouts are online
parameters, and any `rider` login may write them; with the policy `ignore` written during
someone else's ride, a killed supervising Rider no longer paused it. So, for these settings:

- an online write may make one *stricter* than the config file says, never *less strict*
  (less strict needs the config file: a login on the controller, not on the bus);
- while anything moves (a controller or a session, paused included), no write may make one
  less strict than it is now, not even back to the file's value;
- every write of one, taken or refused, is a `safety_changed` event with who asked.

The scan watchdog (`loop.watchdog_periods`, `loop.watchdog_min_s`) and the loop period are no
online parameters at all: the config file alone sets them.
"""

from __future__ import annotations

from enum import Enum

from ride_machine.service.config.model import MachineConfig, RiderLossPolicy
from ride_machine.service.errors import ParamLocked


class Stricter(Enum):
    """Which way a safety setting gets stricter."""

    LOWER = "lower"
    """A shorter timeout or grace, a smaller tolerance, a lower upper limit."""
    HIGHER = "higher"
    """A higher lower limit."""
    POLICY = "policy"
    """The rider-loss policy: `ignore` < `pause` < `stop`."""


SAFETY: dict[str, Stricter] = {
    "rider_loss.policy": Stricter.POLICY,
    "rider_loss.grace_s": Stricter.LOWER,
    "rider_loss.timeout_s": Stricter.LOWER,
    "tilt.min_deg": Stricter.HIGHER,
    "tilt.max_deg": Stricter.LOWER,
    "tilt.home_timeout_s": Stricter.LOWER,
    "tilt.move_timeout_margin_s": Stricter.LOWER,
    "rotate.revolution_timeout_s": Stricter.LOWER,
    "rotate.backoff_timeout_s": Stricter.LOWER,
    "rotate.speed_tolerance": Stricter.LOWER,
}
"""Every safety setting among the online parameters, and which way it gets stricter."""

_POLICY_RANK = {RiderLossPolicy.IGNORE: 0, RiderLossPolicy.PAUSE: 1, RiderLossPolicy.STOP: 2}


CONFIG_ONLY = ("loop.watchdog_periods", "loop.watchdog_min_s", "loop.period_s")
"""Safety settings that are no online parameter at all: the config file alone sets them."""


def in_effect(config: MachineConfig) -> dict[str, bool | int | float | str]:
    """Every safety setting's value in `config` (for the record each start leaves)."""
    out: dict[str, bool | int | float | str] = {}
    for name in (*SAFETY, *CONFIG_ONLY):
        section, field = name.split(".")
        value = getattr(getattr(config, section), field)
        out[name] = value.value if isinstance(value, Enum) else value
    return out


def is_safety(name: str) -> bool:
    return name in SAFETY


def weaker(name: str, value: object, than: object) -> bool:
    """Whether `value` makes safety setting `name` less strict than `than`."""
    way = SAFETY[name]
    if way is Stricter.POLICY:
        return _POLICY_RANK[RiderLossPolicy(str(value))] < _POLICY_RANK[RiderLossPolicy(str(than))]
    assert isinstance(value, int | float) and isinstance(than, int | float)
    return value > than if way is Stricter.LOWER else value < than


def check_write(name: str, value: object, *, live: object, project: object, moving: bool) -> None:
    """Refuse (`ParamLocked`) a write of `value` to safety setting `name` that makes it less
    strict than the config file's `project` value, or, while `moving`, than its `live` one."""
    if weaker(name, value, project):
        raise ParamLocked(
            f"{name} = {value!r} is less strict than the config file's {project!r}: a safety"
            " setting may only be made stricter online; make it less strict in the machine's"
            " config file and restart",
            "/value",
        )
    if moving and weaker(name, value, live):
        raise ParamLocked(
            f"{name} cannot be made less strict ({live!r} -> {value!r}) while the machine is"
            " moving; Stop or wait until it is done, then write again",
            "/value",
        )
