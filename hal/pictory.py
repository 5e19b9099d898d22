"""The piCtory `config.rsc` as a file: its shape, and the module layout revpimodio2 trusts.

revpimodio2 drops a module with a fractional offset, warns once per IO about overlapping
modules and fails with a bare `KeyError` on a module past the process image. These checks read
the file first and say in one finding per problem what happened and how to fix it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from ride_machine.schema.findings import Finding, Severity

from .base import HalConfigError

CONFIG_PATH = "/hal/revpi/configrsc"
IMAGE_BYTES = 4096
"""The size of piControl's process image (`KB_PI_LEN`): no module may reach past it."""
_DEVICE_KEYS = ("type", "productType", "position", "name", "offset", "inp", "out", "mem")
_SHOWN = 4

PRODUCTS = {
    95: "RevPi Core",
    96: "DIO",
    97: "DI",
    98: "DO",
    103: "AIO",
    104: "RevPi Compact",
    105: "RevPi Connect",
    118: "MIO",
    135: "RevPi Flat",
    136: "RevPi Connect 4",
    137: "RO",
    138: "RevPi Connect 5",
}
"""piCtory product types by name, for messages (revpimodio2's `ProductType` has the numbers)."""
BYTE_IO_BASES = frozenset({104, 135})
"""Base modules whose digital IO piCtory lays out as whole bytes: RevPi Compact and Flat."""
STATUS_MODULES = frozenset({95, 96, 97, 98, 105, 136, 137, 138})
"""Modules whose 16-bit input words are status or diagnostics, never an analog value."""


class RevPiConfigError(HalConfigError):
    """The piCtory config, the process image or the IO map does not fit; see `findings`."""


def error(category: str, path: str, message: str) -> Finding:
    return Finding(category=category, severity=Severity.ERROR, path=path, message=message)


def read_config(path: str) -> dict[str, Any]:
    """The parsed config.rsc, checked for the shape revpimodio2 relies on."""

    def bad(why: str) -> RevPiConfigError:
        return RevPiConfigError([error("revpi_config", CONFIG_PATH, f"{path}: {why}")])

    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except OSError as exc:
        raise bad(f"cannot read the piCtory config ({exc.strerror})") from exc
    except UnicodeDecodeError as exc:
        raise bad("not a piCtory config (not UTF-8 text)") from exc
    except json.JSONDecodeError as exc:
        raise bad(f"not valid JSON (line {exc.lineno} column {exc.colno}: {exc.msg})") from exc
    if not isinstance(data, dict):
        raise bad("not a piCtory config (the top level is not a JSON object)")
    shapes = {"App": dict, "Summary": dict, "Devices": list}
    missing = [k for k, kind in shapes.items() if not isinstance(data.get(k), kind)]
    if missing:
        raise bad(f"not a piCtory config (missing or malformed: {', '.join(missing)})")
    for n, device in enumerate(data["Devices"]):
        if not isinstance(device, dict):
            raise bad(f"device #{n} is not a JSON object")
        lacking = [k for k in _DEVICE_KEYS if k not in device]
        if lacking:
            raise bad(f"device #{n} ({device.get('name', '?')}) lacks {', '.join(lacking)}")
        for section in ("inp", "out", "mem"):
            entries = device[section]
            if not isinstance(entries, dict) or not all(
                isinstance(e, list) and len(e) >= 8 for e in entries.values()
            ):
                raise bad(
                    f"device {device['name']!r}: {section!r} must map indexes to IO entries"
                    " [name, default, bitlen, byte, export, idx, bmk, bit]"
                )
    return data


@dataclass(frozen=True)
class Module:
    """One device of the config.rsc as the file states it (before revpimodio2 reads it)."""

    name: str
    position: str
    product: str
    offset: float | None
    """None when the offset is not a number at all."""
    size: int
    """Bytes from the offset to the end of its last IO."""
    ios: tuple[str, ...]

    @property
    def label(self) -> str:
        return f"{self.name!r} ({self.product}, position {self.position})"


def product_name(device: dict[str, Any]) -> str:
    """ "DIO", "RevPi Core", …; gateways and virtual devices by their kind."""
    try:
        code = int(device.get("productType", -1))
    except (TypeError, ValueError):
        code = -1
    if code in PRODUCTS:
        return PRODUCTS[code]
    kind = device.get("type")
    if kind == "EDGE":
        return "gateway"
    if kind == "VIRTUAL":
        return "virtual device"
    return f"product type {device.get('productType')}"


def modules(data: dict[str, Any]) -> list[Module]:
    """Every device of a config that passed `read_config`, in file order."""
    out = []
    for device in data["Devices"]:
        try:
            offset: float | None = float(device["offset"])
        except (TypeError, ValueError):
            offset = None
        size, names = 0, []
        for section in ("inp", "out", "mem"):
            for entry in device[section].values():
                names.append(str(entry[0]))
                size = max(size, _entry_end(entry))
        out.append(
            Module(
                str(device["name"]),
                str(device["position"]),
                product_name(device),
                offset,
                size,
                tuple(names),
            )
        )
    return out


def _entry_end(entry: list[Any]) -> int:
    """The byte after an IO entry [name, default, bitlen, byte, export, idx, bmk, bit]."""
    try:
        byte, bitlen = int(entry[3]), int(entry[2])
        if entry[7] not in ("", None):
            return byte + int(entry[7]) // 8 + 1
    except (TypeError, ValueError):
        return 0
    return byte + max(1, bitlen // 8)


def layout_findings(data: dict[str, Any], path: str) -> list[Finding]:
    """Modules at a fractional or non-numeric offset, overlapping, or past the image."""
    found: list[Finding] = []
    placed: list[Module] = []
    for mod in modules(data):
        if mod.offset is None:
            found.append(
                error(
                    "revpi_layout",
                    CONFIG_PATH,
                    f"{path}: module {mod.label} has offset {_raw_offset(data, mod)!r}, not a"
                    " number; save the configuration again in piCtory",
                )
            )
        elif mod.offset != int(mod.offset):
            found.append(_fractional(data, mod, path))
        else:
            placed.append(mod)
    placed.sort(key=lambda m: m.offset or 0)
    reach: Module | None = None  # the module reaching furthest so far
    for mod in placed:
        before, start = reach, int(mod.offset or 0)
        if reach is None or _end(mod) > _end(reach):
            reach = mod
        end = _end(before) if before is not None else 0
        if before is not None and start < end:
            found.append(
                error(
                    "revpi_layout",
                    CONFIG_PATH,
                    f"{path}: modules {before.label} at bytes {_span(before)} and {mod.label}"
                    f" at bytes {_span(mod)} overlap at bytes {start}–{min(end, _end(mod)) - 1};"
                    " both would read and write the same bytes. The offsets in the file are"
                    f" inconsistent (edited by hand, or a piCtory bug): {mod.name!r} must start"
                    f" at byte {end} or later. Place the modules again in piCtory, save, and"
                    " reset the driver (`piTest -x`)",
                )
            )
    found += _duplicates(data, path)
    for mod in placed:
        if _end(mod) > IMAGE_BYTES:
            found.append(
                error(
                    "revpi_layout",
                    CONFIG_PATH,
                    f"{path}: module {mod.label} at offset {int(mod.offset or 0)} needs bytes"
                    f" {_span(mod)}, past the end of the {IMAGE_BYTES}-byte process image;"
                    " its offset must follow the module before it"
                    f" (byte {_end_before(placed, mod)}). Save the configuration again in piCtory"
                    " and reset the driver (`piTest -x`)",
                )
            )
    return found


def _duplicates(data: dict[str, Any], path: str) -> list[Finding]:
    """IO names used twice: revpimodio2 refuses the whole file over the first one."""
    seen: dict[str, Module] = {}
    found: list[Finding] = []
    for mod in modules(data):
        for name in mod.ios:
            if name in seen and len(found) < _SHOWN:
                found.append(
                    error(
                        "revpi_layout",
                        CONFIG_PATH,
                        f"{path}: the IO name {name!r} is used on module {seen[name].label} and"
                        f" again on {mod.label}; IO names must be unique (piCtory renames a copy"
                        " to e.g. 'I_1_i03'): rename one in piCtory and save",
                    )
                )
            seen.setdefault(name, mod)
    return found


def _fractional(data: dict[str, Any], mod: Module, path: str) -> Finding:
    names = ", ".join(mod.ios[:_SHOWN]) + (", …" if len(mod.ios) > _SHOWN else "")
    whole = [m for m in modules(data) if m.offset is not None and m.offset == int(m.offset)]
    before = [m for m in whole if (m.offset or 0) < (mod.offset or 0)]
    suggest = max((int(m.offset or 0) + m.size for m in before), default=0)
    return error(
        "revpi_layout",
        CONFIG_PATH,
        f"{path}: module {mod.label} has the fractional offset {mod.offset:g}, a known piCtory"
        " 2.1.2 bug; revpimodio2 ignores such a module with all its IOs"
        f" ({len(mod.ios)}: {names}). Fix: update piCtory and save the configuration again,"
        f' or set its "offset" to {suggest} (where the module before it ends) by hand; then'
        " reset the driver (`piTest -x`)",
    )


def _raw_offset(data: dict[str, Any], mod: Module) -> Any:
    for device in data["Devices"]:
        if str(device["name"]) == mod.name and str(device["position"]) == mod.position:
            return device["offset"]
    return None


def _end(mod: Module) -> int:
    return int(mod.offset or 0) + mod.size


def _span(mod: Module) -> str:
    return f"{int(mod.offset or 0)}–{_end(mod) - 1}"


def _end_before(placed: list[Module], mod: Module) -> int:
    before = [m for m in placed if (m.offset or 0) < (mod.offset or 0)]
    return max((_end(m) for m in before), default=0)


def io_modules(data: dict[str, Any]) -> dict[str, Module]:
    """IO name → the module the file puts it on (the first one, if a name repeats)."""
    out: dict[str, Module] = {}
    for mod in modules(data):
        for name in mod.ios:
            out.setdefault(name, mod)
    return out
