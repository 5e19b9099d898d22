"""Online parameters: project defaults from the config, live values, persisted overrides."""

from __future__ import annotations

import builtins
import logging
import math
import threading
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

import annotated_types as at
from pydantic import BaseModel, ValidationError

from ride_machine.schema.fastdata import INT32_MAX, INT32_MIN, USER_REGISTER_LENGTH
from ride_machine.schema.findings import Severity
from ride_machine.schema.params import ParamSet, ParamValue
from ride_machine.service.config.model import LiveConfig, MachineConfig
from ride_machine.service.config.validate import semantic_findings
from ride_machine.service.errors import (
    ParamLocked,
    ParamOutOfRange,
    ParamWrongType,
    StorageFailed,
    UnknownParam,
)

from .atomic import NotDurable
from .persist import ParamScalar, ParamStore, StorageHealth, StoredParam
from .safety import check_write, is_safety, weaker

log = logging.getLogger(__name__)


# (name, unit, locked while moving, description). Type, bounds and default come from the
# config model, so a range is written down once. loop.period_s is deliberately absent: the
# runner's timing and the validation of the period hold for one period per process.
_ONLINE: tuple[tuple[str, str, bool, str], ...] = (
    ("tilt.tolerance_deg", "°", True, "settle window (±) around a tilt target"),
    ("tilt.nominal_speed_dps", "°/s", True, "tilt speed, for timeouts and calibration"),
    ("tilt.min_deg", "°", True, "lowest tilt a session may ask for"),
    ("tilt.max_deg", "°", True, "highest tilt a session may ask for"),
    ("tilt.home_timeout_s", "s", False, "time allowed to reach the tilt home switch"),
    ("tilt.move_timeout_margin_s", "s", False, "slack added to every tilt move's timeout"),
    ("rotate.nominal_speed_dps", "°/s", True, "rotate speed, for timeouts and calibration"),
    ("rotate.speed_tolerance", "", True, "accepted revolution-time deviation (fraction)"),
    ("rotate.revolution_timeout_s", "s", False, "time allowed for one revolution"),
    ("rotate.backoff_timeout_s", "s", False, "time allowed to leave the rotate home switch"),
    ("bus.heartbeat_s", "s", False, "status is republished at least this often"),
    ("rider_loss.policy", "", False, "what to do when the controlling Rider disappears"),
    ("rider_loss.grace_s", "s", False, "how long a lost Rider may take to come back"),
    ("rider_loss.timeout_s", "s", False, "silence of the controlling Rider's heartbeat = lost"),
)


@dataclass(frozen=True)
class ParamSpec:
    """One online parameter: where it lives in the config, its type, unit and bounds."""

    name: str
    section: str
    field: str
    kind: type
    unit: str
    description: str
    locked_while_moving: bool
    minimum: float | None = None
    maximum: float | None = None
    min_exclusive: bool = False
    max_exclusive: bool = False
    choices: tuple[str, ...] = ()
    index: int | None = None
    """For an element of a list field (the FastData user registers): its position."""

    def default(self, config: MachineConfig) -> ParamScalar:
        """The value in `config` (enums as their string; a missing list element is zero)."""
        value = getattr(getattr(config, self.section), self.field)
        if self.index is not None:
            return _scalar(value[self.index]) if self.index < len(value) else self.kind(0)
        return value.value if isinstance(value, StrEnum) else _scalar(value)

    def check(self, value: object) -> ParamScalar:
        """The value in this parameter's type, or ParamWrongType / ParamOutOfRange."""
        if self.choices:
            if not isinstance(value, str):
                raise self._wrong(value, "one of " + ", ".join(self.choices))
            if value not in self.choices:
                raise ParamOutOfRange(
                    f"{self.name} must be one of {', '.join(self.choices)}; got {value!r}",
                    "/value",
                )
            return value
        if self.kind is bool:
            if not isinstance(value, bool):
                raise self._wrong(value, "true or false")
            return value
        # bool is an int in Python, but `true` is never a number on the wire.
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self._wrong(value, "an integer" if self.kind is int else "a number")
        if self.kind is int and not isinstance(value, int):
            raise self._wrong(value, "an integer")
        try:
            number: float | int = float(value) if self.kind is float else value
        except OverflowError:  # an integer of 309 digits or more (JSON allows it): no float
            bounded = self.minimum is not None or self.maximum is not None
            wanted = self.range_text() if bounded else "a finite number"
            raise ParamOutOfRange(
                f"{self.name} must be {wanted}; got {_num(value)}", "/value"
            ) from None
        if isinstance(number, float) and not math.isfinite(number):
            raise ParamOutOfRange(f"{self.name} must be a finite number; got {number:g}", "/value")
        if not self._in_range(number):
            raise ParamOutOfRange(
                f"{self.name} must be {self.range_text()}; got {_num(number)}", "/value"
            )
        return number

    def range_text(self) -> str:
        """E.g. `> 0 and ≤ 10 °`."""
        parts = []
        if self.minimum is not None:
            parts.append(f"{'>' if self.min_exclusive else '≥'} {_num(self.minimum)}")
        if self.maximum is not None:
            parts.append(f"{'<' if self.max_exclusive else '≤'} {_num(self.maximum)}")
        text = " and ".join(parts) or "any number"
        return f"{text} {self.unit}".rstrip()

    def _in_range(self, v: float) -> bool:
        lo, hi = self.minimum, self.maximum
        if lo is not None and (v <= lo if self.min_exclusive else v < lo):
            return False
        return not (hi is not None and (v >= hi if self.max_exclusive else v > hi))

    def _wrong(self, value: object, expected: str) -> ParamWrongType:
        return ParamWrongType(
            f"{self.name} expects {expected}; got {type(value).__name__} {value!r}", "/value"
        )


def _num(v: float) -> str:
    """`0.5`, `10`, and whole numbers in full (an int32 bound, not `2.14748e+09`); an int too
    long to be worth printing (or for `str`) by its size."""
    if isinstance(v, int):
        return str(v) if abs(v) < 10**30 else f"an integer of {len(hex(v)) * 4 - 8}+ bits"
    return str(int(v)) if v.is_integer() else f"{v:g}"


def _scalar(value: object) -> ParamScalar:
    if isinstance(value, bool | int | float | str):
        return value
    raise TypeError(f"not a parameter value: {value!r}")


def _spec(name: str, unit: str, locked: bool, description: str) -> ParamSpec:
    section, field = name.split(".")
    section_model = MachineConfig.model_fields[section].annotation
    assert isinstance(section_model, type) and issubclass(section_model, BaseModel)
    info = section_model.model_fields[field]
    kind = info.annotation
    assert isinstance(kind, type), f"{name}: optional or union fields cannot be parameters"
    bounds: dict[str, Any] = {}
    for m in info.metadata:
        if isinstance(m, at.Gt):
            bounds.update(minimum=float(m.gt), min_exclusive=True)  # type: ignore[arg-type]
        elif isinstance(m, at.Ge):
            bounds.update(minimum=float(m.ge))  # type: ignore[arg-type]
        elif isinstance(m, at.Lt):
            bounds.update(maximum=float(m.lt), max_exclusive=True)  # type: ignore[arg-type]
        elif isinstance(m, at.Le):
            bounds.update(maximum=float(m.le))  # type: ignore[arg-type]
    choices = tuple(e.value for e in kind) if issubclass(kind, StrEnum) else ()
    return ParamSpec(
        name, section, field, kind, unit, description, locked, choices=choices, **bounds
    )


def _register_specs() -> list[ParamSpec]:
    """`fastdata.int.<i>` and `fastdata.double.<i>`: the FastData user registers (seed 002)."""
    ints = [
        ParamSpec(
            f"fastdata.int.{i}",
            "fastdata",
            "user_ints",
            int,
            "",
            f"FastData user register int_array[{i}], sent in every reply",
            False,
            minimum=INT32_MIN,
            maximum=INT32_MAX,
            index=i,
        )
        for i in range(USER_REGISTER_LENGTH)
    ]
    doubles = [
        ParamSpec(
            f"fastdata.double.{i}",
            "fastdata",
            "user_doubles",
            float,
            "",
            f"FastData user register double_array[{i}], sent in every reply",
            False,
            index=i,
        )
        for i in range(USER_REGISTER_LENGTH)
    ]
    return ints + doubles


SPECS: dict[str, ParamSpec] = {row[0]: _spec(*row) for row in _ONLINE} | {
    spec.name: spec for spec in _register_specs()
}
"""Every online parameter by its dotted name, in a stable order."""


def _errors(config: MachineConfig, own_path: str) -> set[tuple[int, str, str, str]]:
    """The file check's errors, and its warnings about the written field itself (errors sort
    first): an online write has nobody to read a warning, so a value the file check flags at
    its own path (`bus.heartbeat_s` 1e-9: "cannot be held") is refused, not taken silently."""
    return {
        (f.severity is not Severity.ERROR, f.category, f.path, f.message)
        for f in semantic_findings(config)
        if f.severity is Severity.ERROR or f.path == own_path
    }


class ParamRegistry:
    """The live parameters of one machine; thread-safe, so the bus may call it directly.

    The project config stays as loaded; `config` is it with the live values applied, and
    `live` is the holder the machine reads it from (it takes a new one at a cycle boundary).
    """

    def __init__(
        self, config: MachineConfig, store: ParamStore, health: StorageHealth | None = None
    ) -> None:
        self._project = config
        self._store = store
        self._health = health
        self._lock = threading.Lock()
        self._live: dict[str, ParamScalar] = {}
        self._changed_at: dict[str, float | None] = {}
        self._stored: dict[str, StoredParam] = {}
        self._config = config
        self.warnings: builtins.list[str] = self._load()
        self.live = LiveConfig(self._config)
        """What the machine runs with: each accepted write is offered to it."""

    @property
    def config(self) -> MachineConfig:
        """The project config with every live value applied (validated, immutable)."""
        return self._config

    @property
    def project(self) -> MachineConfig:
        """The config as loaded from the file: the project defaults."""
        return self._project

    def names(self) -> builtins.list[str]:
        return builtins.list(SPECS)

    def list(self) -> builtins.list[ParamValue]:
        """Every parameter's live record."""
        with self._lock:
            return [self._record(spec) for spec in SPECS.values()]

    def get(self, name: str) -> ParamValue:
        """One parameter's live record, or UnknownParam."""
        spec = _lookup(name)
        with self._lock:
            return self._record(spec)

    def set(self, name: str, req: ParamSet, *, moving: bool, now: float) -> ParamValue:
        """Write (or reset) a parameter; nothing changes unless every check and the disk agree.

        `moving`: a controller or session is active (paused included): parameters that are
        `locked_while_moving` are refused. `now` is the wall time recorded as `changed_at`.
        """
        spec = _lookup(name)
        if req.reset and req.value is not None:
            raise ParamWrongType(f"{name}: a reset takes no value", "/value")
        if not req.reset and req.value is None:
            raise ParamWrongType(f"{name}: give a value, or reset: true", "/value")
        value = None if req.reset else spec.check(req.value)
        if moving and spec.locked_while_moving:
            raise ParamLocked(
                f"{name} cannot change while the machine is moving; Stop or wait until it is"
                " done, then write again",
                "/value",
            )
        with self._lock:
            if is_safety(name):  # only stricter online (service/core/storage/safety.py)
                project = spec.default(self._project)
                live_value = self._live.get(name, project)
                target = project if value is None else value
                check_write(name, target, live=live_value, project=project, moving=moving)
            live = dict(self._live)
            if value is None:
                live.pop(name, None)
            else:
                live[name] = value
            candidate = self._candidate(live, spec, value)
            stored = dict(self._stored)
            if req.reset:
                stored.pop(name, None)
            elif req.persist:
                assert value is not None
                stored[name] = StoredParam(value, now)
            if stored != self._stored:
                self._save(stored, name)
            self._live, self._stored, self._config = live, stored, candidate
            self.live.offer(candidate)
            self._changed_at[name] = None if req.reset else now
            log.info(
                "event=param_set name=%s value=%r persist=%s reset=%s",
                name,
                value,
                req.persist,
                req.reset,
            )
            return self._record(spec)

    # ----------------------------------------------------------------------- internals
    def _record(self, spec: ParamSpec) -> ParamValue:
        value = self._live.get(spec.name, spec.default(self._project))
        stored = self._stored.get(spec.name)
        return ParamValue(
            name=spec.name,
            value=value,
            default=spec.default(self._project),
            persisted=stored is not None and stored.value == value,
            changed_at=self._changed_at.get(spec.name),
            unit=spec.unit,
            minimum=spec.minimum,
            maximum=spec.maximum,
            locked_while_moving=spec.locked_while_moving,
            description=spec.description
            + (f" (one of {', '.join(spec.choices)})" if spec.choices else ""),
        )

    def _candidate(
        self, live: dict[str, ParamScalar], spec: ParamSpec, value: ParamScalar | None
    ) -> MachineConfig:
        """The config with `live` applied, refused if it breaks a cross-field check."""
        sections: dict[str, dict[str, Any]] = {}
        for name, v in live.items():
            s = SPECS[name]
            fields = sections.setdefault(s.section, {})
            if s.index is None:
                fields[s.field] = v
                continue
            items = fields.setdefault(
                s.field, list(getattr(self._project, s.section).__dict__[s.field])
            )
            items.extend([s.kind(0)] * (s.index + 1 - len(items)))
            items[s.index] = v
        shown = f"{spec.name}={value!r}" if value is not None else f"{spec.name} reset"
        try:
            candidate = self._project.with_overrides(**sections)
        except ValidationError as exc:
            raise ParamOutOfRange(f"{shown}: {exc.errors()[0]['msg']}", "/value") from exc
        own = f"/{spec.section}/{spec.field}"
        new = sorted(_errors(candidate, own) - _errors(self._config, own))
        if new:
            _, _, path, message = new[0]
            raise ParamOutOfRange(f"{shown} conflicts with {path}: {message}", "/value")
        return candidate

    def _save(self, stored: dict[str, StoredParam], name: str) -> None:
        try:
            self._store.save(stored)
        except NotDurable as exc:
            # The new file is what is read now (and, likely, after a restart): the value is
            # taken, as the file has it, and the doubt about a power cut is said.
            message = (
                f"{name}: written to {self._store.path}, but its directory could not be synced"
                f" ({exc.strerror or exc}): a power cut may lose it"
            )
            log.error("event=persist_not_durable what=params detail=%r", message)
            if self._health is not None:
                self._health.failed(StorageHealth.PARAMS, message)
            return
        except OSError as exc:
            message = (
                f"{name}: could not write {self._store.path} ({exc.strerror or exc});"
                " nothing was changed"
            )
            log.error("event=persist_failed what=params detail=%r", message)
            if self._health is not None:
                self._health.failed(StorageHealth.PARAMS, message)
            raise StorageFailed(message, "/persist") from exc
        if self._health is not None:
            self._health.recovered(StorageHealth.PARAMS)

    def _load(self) -> builtins.list[str]:
        """Apply the persisted overrides one by one; each one that no longer fits is a warning."""
        entries, warnings = self._store.load()
        path = self._store.path
        for name, entry in entries.items():
            spec = SPECS.get(name)
            try:
                if spec is None:
                    raise UnknownParam("not an online parameter")
                value = spec.check(entry.value)
                project = spec.default(self._project)
                if is_safety(name) and weaker(name, value, project):
                    raise ParamOutOfRange(f"less strict than the config file's {project!r}")
                live = {**self._live, name: value}
                self._config = self._candidate(live, spec, value)
            except (UnknownParam, ParamWrongType, ParamOutOfRange) as exc:
                default = f"the default {spec.default(self._project)!r}" if spec else "nothing"
                warnings.append(
                    f"{path}: persisted {name}={entry.value!r} ignored ({exc.message});"
                    f" using {default}"
                )
                continue
            self._live[name] = value
            self._stored[name] = StoredParam(value, entry.changed_at)
            self._changed_at[name] = entry.changed_at
        for w in warnings:
            log.warning("event=params_load detail=%r", w)
        return warnings


def _lookup(name: str) -> ParamSpec:
    spec = SPECS.get(name)
    if spec is None:
        raise UnknownParam(f"unknown parameter {name!r}; known: {', '.join(SPECS)}")
    return spec
