"""The machine config (`machine.toml`): pydantic models with the project defaults."""

from __future__ import annotations

import tomllib
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any, Protocol, cast

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_core import ErrorDetails, InitErrorDetails, PydanticCustomError

from ride_machine.hal.backends import names, settings_of
from ride_machine.hal.iomap import IoMap
from ride_machine.hal.revpibackend import RevPiSettings
from ride_machine.schema.fastdata import INT32_MAX, INT32_MIN, USER_REGISTER_LENGTH

from .axes import RotateSection, TiltSection
from .section import _Section

Int32 = Annotated[int, Field(ge=INT32_MIN, le=INT32_MAX)]
Finite = Annotated[float, Field(allow_inf_nan=False)]


class MachineSection(_Section):
    """Identity on the bus: keys are `<key_prefix>/<id>/...`."""

    id: str = Field(default="m1", pattern=r"^[A-Za-z0-9_\-]{1,32}$")
    key_prefix: str = Field(default="machine", pattern=r"^[A-Za-z0-9_\-]+(/[A-Za-z0-9_\-]+)*$")


MIN_SLICE_S = 0.0001
"""The shortest time slice the kernel grants (it clamps a shorter request up to it)."""


class LoopSection(_Section):
    """The scan task: period, and the real-time measures that help hold short periods."""

    period_s: float = Field(default=0.010, ge=0.001, le=1.0)
    spin_s: float = Field(default=0.0, ge=0.0, le=0.005)
    gc_freeze: bool = True
    gc_threshold: int = Field(default=10_000, ge=100, le=1_000_000)
    """Young objects that start a garbage collection (`gc.set_threshold`'s first value;
    Python's default 700). A command stream keeps ~15 objects per command in flight to the
    event writer: at 700 a collection ran every batch, ~45 a second (BENCHMARKS.md section 1)."""
    switch_interval_s: float = Field(default=0.0005, ge=0.0001, le=0.1)
    """How long another Python thread (a command's callback under a storm) may keep the GIL
    once the scan thread wants it (`sys.setswitchinterval`; Python's default is 5 ms)."""
    cpu: int | None = Field(default=None, ge=0)
    cpus: list[Annotated[int, Field(ge=0)]] | None = Field(default=None, min_length=1)
    """Pin the whole daemon (every thread: Zenoh's, the command callbacks, the event and log
    writers, the scan) to these CPUs, from its start; `cpu` then pins the scan thread alone.
    On two cores, one CPU for the daemon cut a command's round trip by 23-39 µs in a timeline
    harness and by nothing in the committed `bench.roundtrip` run, and it lengthens a 1 ms
    loop's jitter unless `cpu` gives the scan thread the other core (BENCHMARKS.md sections 1
    and 2): an option, not a default."""
    rt_priority: int | None = Field(default=None, ge=1, le=99)
    slice_s: float = Field(default=MIN_SLICE_S, ge=0.0, le=0.1)
    """Every daemon thread's time slice under the normal policy (Linux 6.12+, no privilege): a
    short one lets a wake-up preempt a busy neighbour at once (BENCHMARKS.md section 2). 0
    keeps the kernel's (1.4 ms on two CPUs); below `MIN_SLICE_S` is a finding."""
    watchdog_periods: int = Field(default=3, ge=2, le=1000)
    watchdog_min_s: float = Field(default=0.1, ge=0.0, le=10.0)
    """The watchdog limit is never shorter than this. 0.1 s: a 2-core host beside two
    CPU-bound processes stalled an idle daemon's scan 40-150 ms (BENCHMARKS.md, freeze); a
    moving tilt covers 1.5° and the rotate 9° in it at the nominal speeds."""
    max_commands_per_cycle: int = Field(default=64, ge=1, le=10_000)
    stats_window: int = Field(default=1000, ge=10, le=100_000)
    malloc_arenas: int | None = Field(default=None, ge=1, le=1024)
    """Cap glibc's malloc arenas at start (None: glibc's default, 8 per core). 2 keeps RSS flat
    under heavy Rider connect churn, but slowed the scan's execution 5-10 % under motion load
    (BENCHMARKS.md section 5); `MALLOC_ARENA_MAX` in the environment wins."""

    @property
    def watchdog_limit_s(self) -> float:
        """How long the scan may go without completing a cycle before a stall is declared
        (the in-process watchdog, the scan's own check and the supervisor's output guard)."""
        return max(self.period_s * self.watchdog_periods, self.watchdog_min_s)

    @property
    def slice_ns(self) -> int | None:
        """`slice_s` for `tune_thread`: None keeps the kernel's."""
        return round(self.slice_s * 1e9) or None


class RiderLossPolicy(StrEnum):
    """What the machine does when the controlling Rider disappears mid-motion."""

    PAUSE = "pause"
    STOP = "stop"
    IGNORE = "ignore"


class RiderLossSection(_Section):
    """Supervision of the Rider that started a motion: its heartbeat, and what its loss does."""

    policy: RiderLossPolicy = RiderLossPolicy.PAUSE
    grace_s: float = Field(default=0.0, ge=0.0, le=60.0)
    timeout_s: float = Field(default=0.5, gt=0.0, le=60.0)
    """The controlling Rider is lost when its heartbeat has been silent this long."""


class BusSection(_Section):
    """Publication rates of the Zenoh adapter."""

    heartbeat_s: float = Field(default=1.0, gt=0, le=60)
    diag_period_s: float = Field(default=1.0, gt=0, le=60)
    axis_every_cycles: int = Field(default=1, ge=1, le=10_000)
    ai_deadband_counts: int = Field(default=2, ge=0, le=65_535)
    transaction_window: int = Field(default=4096, ge=1, le=1_000_000)
    inbox_capacity: int = Field(default=1024, ge=1, le=1_000_000)
    confirm_timeout_s: float = Field(default=0.5, gt=0, le=10)
    """How long the machine waits for a Rider named in a request to confirm that it sent it
    (`rider/<login>/<zid>/confirm`, service/bus/confirm.py) before a motion command naming it is
    refused `RIDER_UNCONFIRMED`. A Rider on the bus answers in about a millisecond; for one that
    is not there the machine asks again every 5 ms until this timeout (a Rider's queryable can
    reach it just after its first request)."""
    clock_margin_s: float = Field(default=1.0, ge=0, le=86_400)
    """How far a sender's clock may be behind this machine's before its motion commands look
    older than their `valid_for` and are refused `STALE_REQUEST`."""
    zenoh_threads: int = Field(default=1, ge=0, le=64)
    """Zenoh's worker threads in the daemon: all of its runtimes (receive, send, network,
    accept, application) handed over to one pool of this many threads; 0 keeps Zenoh's own
    layout (five runtimes, six threads). Set as the daemon starts (`ZENOH_RUNTIME`, which wins
    when the environment already has it)."""


class EventsSection(_Section):
    """The event history in `<data_dir>/events.db`: queue, batching, retention, query pages."""

    enabled: bool = True
    process: bool = True
    """Make and write the events in a process of their own (service/adapters/history.py), off
    the daemon's GIL and CPU time slices; false: on a thread of the daemon."""
    queue_capacity: int = Field(default=4096, ge=16, le=1_000_000)
    batch_max: int = Field(default=512, ge=1, le=100_000)
    max_age_days: float = Field(default=90.0, gt=0, le=36_500)
    max_mb: float = Field(default=64.0, ge=1, le=1_000_000)
    """The whole file; routine events (commands, states, completions, sessions) are pruned,
    oldest first, to stay under it. The safety record is not (service/adapters/retention.py)."""
    safety_max_age_days: float = Field(default=730.0, gt=0, le=36_500)
    """E-stops, faults, the watchdog, Riders lost, safety-setting writes, the daemon's starts
    and stops: kept this long, whatever routine traffic comes after them."""
    safety_max_mb: float = Field(default=16.0, ge=0.1, le=1_000_000)
    """The safety record's own size limit (the events a `rider` login can cause go first)."""
    prune_every_s: float = Field(default=60.0, ge=0.1, le=86_400)
    page_max: int = Field(default=500, ge=1, le=10_000)


class HalBackend(StrEnum):
    """The backends this project ships (pyproject.toml registers them). `hal.backend` may name
    any registered backend: a third is one entry point (`hal.backends`)."""

    SIM = "sim"
    REVPI = "revpi"


class SimView(Protocol):
    """What the config's own check reads of `[hal.sim]` (`validate._simulator`)."""

    @property
    def rotate_speed_dps(self) -> float: ...

    @property
    def home_arc_deg(self) -> float: ...

    @property
    def tilt_max_deg(self) -> float: ...

    @property
    def charge_pump_timeout_s(self) -> float: ...

    @property
    def tilt_speed_dps(self) -> float: ...

    @property
    def tilt_home_deg(self) -> float: ...

    @property
    def ai_offset_counts(self) -> float: ...

    @property
    def ai_gain_counts_per_deg(self) -> float: ...


class HalSection(_Section):
    """`[hal]`: the backend, the IO map, and one table per backend, `[hal.<name>]`, each
    validated by the model its backend registers (`hal.backends.settings_of`). Only the chosen
    backend's table is validated (and its backend loaded) as the config is: a hardware install
    never loads the simulator for a `[hal.sim]` table it does not use. A table that names no
    registered backend is refused."""

    model_config = ConfigDict(extra="allow", frozen=True)

    backend: str = HalBackend.SIM
    iomap: IoMap = IoMap()

    @field_validator("backend")
    @classmethod
    def _registered(cls, name: str) -> str:
        if name not in names():  # out of range, as an enum's value would be
            expected = " or ".join(repr(n) for n in sorted(names()))
            raise PydanticCustomError(
                "enum",
                "Input should be {expected} (a registered HAL backend)",
                {"expected": expected},
            )
        return HalBackend(name) if name in HalBackend.__members__.values() else name

    @model_validator(mode="after")
    def _tables(self) -> HalSection:
        extra = self.__pydantic_extra__ or {}
        unknown = [
            InitErrorDetails(
                type=PydanticCustomError(
                    "hal_backend",
                    "a table for no registered HAL backend (known: {known})",
                    {"known": known()},
                ),
                loc=(name,),
                input=raw,
            )
            for name, raw in extra.items()
            if name not in names()
        ]
        if unknown:
            raise ValidationError.from_exception_data("HalSection", unknown)
        self._validate(self.backend)
        return self

    def __eq__(self, other: object) -> bool:
        """Equal when they run the same backend on the same IO with the same tables, as their
        models read them (a table given as its defaults equals none)."""
        if not isinstance(other, HalSection):
            return NotImplemented
        tables = {self.backend, other.backend, *self._given(), *other._given()}
        return (self.backend, self.iomap) == (other.backend, other.iomap) and all(
            self.table(n) == other.table(n) for n in tables
        )

    def __hash__(self) -> int:
        return hash((self.backend, self.iomap))  # what equal sections share

    def _given(self) -> list[str]:
        return list(self.__pydantic_extra__ or {})

    def table(self, name: str) -> BaseModel:
        """`[hal.<name>]`, validated by backend `name`'s model (loading that backend once); its
        defaults when the file has no such table."""
        name = str(name)
        extra = self.__pydantic_extra__ if self.__pydantic_extra__ is not None else {}
        found = extra.get(name)
        return found if isinstance(found, BaseModel) else self._validate(name)

    def settings(self) -> BaseModel:
        """The `[hal.<backend>]` table of the backend that runs (`Backend.open` reads it)."""
        return self.table(self.backend)

    @property
    def sim(self) -> SimView:
        """`[hal.sim]` (the simulator's mechanics; loads the simulator)."""
        return cast("SimView", self.table(HalBackend.SIM))

    @property
    def revpi(self) -> RevPiSettings:
        """`[hal.revpi]` (where revpimodio2 finds the process image)."""
        return cast("RevPiSettings", self.table(HalBackend.REVPI))

    def _validate(self, name: str) -> BaseModel:
        name = str(name)
        extra = self.__pydantic_extra__ if self.__pydantic_extra__ is not None else {}
        raw = extra.get(name, {})
        if isinstance(raw, BaseModel):
            return raw
        try:
            table = settings_of(name).model_validate(raw)
        except ValidationError as exc:
            raise ValidationError.from_exception_data(
                "HalSection", [_under(name, e) for e in exc.errors()]
            ) from None
        extra[name] = table  # validated once: the same object each time it is read
        if self.__pydantic_extra__ is None:
            object.__setattr__(self, "__pydantic_extra__", extra)
        return table


def _under(name: str, error: ErrorDetails) -> InitErrorDetails:
    """A table's error, located under `[hal.<name>]`."""
    return InitErrorDetails(
        type=error["type"],
        loc=(name, *error["loc"]),
        input=error["input"],
        ctx=error.get("ctx", {}),
    )


def known() -> str:
    return ", ".join(sorted(names())) or "none"


class FastDataSection(_Section):
    enabled: bool = False
    host: str = "0.0.0.0"
    port: int = Field(default=60000, ge=1, le=65535)
    # Version 1's user registers, sent in every reply; missing entries read as 0.
    user_ints: list[Int32] = Field(default_factory=list, max_length=USER_REGISTER_LENGTH)
    user_doubles: list[Finite] = Field(default_factory=list, max_length=USER_REGISTER_LENGTH)


class MachineConfig(_Section):
    """Everything a machine daemon needs; every field has a project default."""

    machine: MachineSection = MachineSection()
    loop: LoopSection = LoopSection()
    rotate: RotateSection = RotateSection()
    tilt: TiltSection = TiltSection()
    rider_loss: RiderLossSection = RiderLossSection()
    bus: BusSection = BusSection()
    hal: HalSection = Field(default_factory=HalSection)
    fastdata: FastDataSection = FastDataSection()
    events: EventsSection = EventsSection()
    data_dir: str = Field(default="data", min_length=1)

    @property
    def key_base(self) -> str:
        """`machine/<id>`: the root of this machine's keys."""
        return f"{self.machine.key_prefix}/{self.machine.id}"

    def with_overrides(self, **sections: dict[str, Any]) -> MachineConfig:
        """A copy with some section fields replaced (validated again)."""
        data = self.model_dump(by_alias=True)
        for name, fields in sections.items():
            data[name] = {**data.get(name, {}), **fields}
        return MachineConfig.model_validate(data)


def read_toml(path: Path) -> dict[str, Any]:
    """The raw TOML of a config file (no validation)."""
    with path.open("rb") as fh:
        return tomllib.load(fh)


class LiveConfig:
    """The config the machine runs with: one holder that every reader (control, axes, loop)
    looks at, instead of each keeping its own copy.

    Online parameter writes `offer` a new, validated config from any thread; the scan loop
    `take`s the latest offer at a cycle boundary, so one cycle sees one config.
    """

    def __init__(self, config: MachineConfig) -> None:
        self.current = config
        """The config the machine runs with now; only `take` sets it (a plain attribute: the
        loop reads it every cycle)."""
        self.offered = config
        """The latest offer (`take` makes it current)."""

    def offer(self, config: MachineConfig) -> None:
        """A new config for the next cycle (one reference swap: safe from any thread)."""
        self.offered = config

    def take(self) -> None:
        """On the scan thread, between cycles: run with the latest offer from now on."""
        self.current = self.offered
