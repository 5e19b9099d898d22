"""The IO map bound to piCtory IOs: each signal to an IO (or one bit of one) of the kind it needs,
and what does not fit said with the candidates that would; outputs shared with other programs."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ride_machine.schema.findings import Finding, Severity
from ride_machine.schema.io import IoKind

from .iomap import ANALOG_INPUTS, DIGITAL_INPUTS, OPTIONAL_OUTPUTS, RELAY_OUTPUTS, IoMap, Signal
from .pictory import BYTE_IO_BASES, CONFIG_PATH, STATUS_MODULES, Module, error, product_name
from .revpi_open import import_revpimodio2

KIND = {
    **dict.fromkeys(DIGITAL_INPUTS, IoKind.DI),
    **dict.fromkeys(ANALOG_INPUTS, IoKind.AI),
    **dict.fromkeys(RELAY_OUTPUTS, IoKind.RO),
    **dict.fromkeys(OPTIONAL_OUTPUTS, IoKind.RO),
}
"""The kind of IO each signal needs."""
_WANTED = {
    IoKind.DI: "a digital input (one bit of an input module, e.g. I_1 of a DIO)",
    IoKind.AI: "an analog input: a 16-bit input word, e.g. InputValue_1 of an AIO",
    IoKind.RO: "a digital output (one bit of an output module, e.g. O_1 of a DIO)",
}
_MODULE_FOR = {IoKind.DI: "DI or DIO module", IoKind.RO: "DO, DIO or RO module"}
_ANALOG_FIRST = frozenset({"AIO", "MIO"})
_NOT_DIGITAL = ("Status", "Temperature", "Frequency", "LED")
"""Words in the names of a Compact's or Flat's status bytes: never offered as bit IOs."""
_CANDIDATES = 6


@dataclass(frozen=True)
class BoundIo:
    """A logical signal and the revpimodio2 IO it resolved to.

    `bit` is set when the channel names one bit of a byte or word (`"DIn.3"`): the RevPi
    Compact and Flat lay out their digital IO as whole bytes.
    """

    signal: Signal
    channel: str
    io: Any
    bit: int | None = None

    @property
    def byte(self) -> int:
        """The absolute byte of the process image that holds this bit (or word)."""
        return int(self.io.address) + (self.bit // 8 if self.bit is not None else 0)

    @property
    def mask(self) -> int:
        """This bit within `byte`."""
        return int(self.io._bitshift) if self.bit is None else 1 << self.bit % 8

    def read_bool(self) -> bool:
        """The bit from revpimodio2's copy of the image (after its `readprocimg`)."""
        if self.bit is None:
            return bool(self.io.value)
        return bool(int.from_bytes(self.io.get_value(), "little") >> self.bit & 1)

    def write_bool(self, on: bool) -> None:
        """Set the bit in revpimodio2's buffer (its `writeprocimg` writes it)."""
        if self.bit is None:
            self.io.value = on
            return
        raw = self.io.get_value()
        value = int.from_bytes(raw, "little")
        value = value | 1 << self.bit if on else value & ~(1 << self.bit)
        self.io.set_value(value.to_bytes(len(raw), "little"))

    def default_on(self) -> bool:
        """Whether piCtory's default value switches this bit on."""
        default = self.io.get_defaultvalue()
        if self.bit is None:
            return bool(default)
        return bool(int.from_bytes(bytes(default or b""), "little") >> self.bit & 1)


def _resolve(rpi: Any, channel: str) -> tuple[Any, int | None] | None:
    """The IO a channel names (`"I_1"`), or a byte IO and one of its bits (`"DIn.3"`)."""
    from revpimodio2.io import IOBase

    io = getattr(rpi.io, channel, None)  # IOList has no .get; names are attributes
    if isinstance(io, IOBase):
        return io, None
    name, dot, bit = channel.rpartition(".")
    if dot and bit.isdigit():
        io = getattr(rpi.io, name, None)
        if isinstance(io, IOBase):
            return io, int(bit)
    return None


def bind_ios(
    rpi: Any, iomap: IoMap, known: Mapping[str, Module] | None = None
) -> tuple[list[BoundIo], list[Finding]]:
    """Resolve every signal of the IO map to a piCtory IO of the right kind.

    In simulator mode revpimodio2 swaps inputs and outputs, so the kinds are checked as the
    real device sees them. `known` (IO name → module, from the file) explains a name that is
    in the file but that revpimodio2 ignored.
    """
    rp = import_revpimodio2()
    directions = (rp.OUT, rp.INP) if rpi.simulator else (rp.INP, rp.OUT)
    bound: list[BoundIo] = []
    findings: list[Finding] = []
    for signal in iomap.mapped():
        kind = KIND[signal]
        channel = iomap.channel(signal)
        path = f"/hal/iomap/{signal.value}"
        found = _resolve(rpi, channel)
        if found is None:
            findings.append(_missing(rpi, signal, channel, known or {}, directions))
            continue
        io, bit = found
        problem = _misfit(io, bit, kind, directions)
        if problem is not None:
            findings.append(
                error("io_type", path, f"{signal.value} must be {_WANTED[kind]}, but {problem}")
            )
            continue
        b = BoundIo(signal, channel, io, bit)
        if kind is IoKind.RO and b.default_on():
            findings.append(
                Finding(
                    category="io_default",
                    severity=Severity.WARNING,
                    path=path,
                    message=f"{channel!r} has default value 1 in piCtory, so piControl switches"
                    " it on before the daemon runs; set its default to 0",
                )
            )
        bound.append(b)
    return bound, findings


def _missing(
    rpi: Any,
    signal: Signal,
    channel: str,
    known: Mapping[str, Module],
    directions: tuple[int, int],
) -> Finding:
    path = f"/hal/iomap/{signal.value}"
    mod = known.get(channel) or known.get(channel.rpartition(".")[0])
    if mod is not None:
        return error(
            "io_missing",
            path,
            f"{signal.value} is mapped to {channel!r}, which is on module {mod.label} in the"
            " piCtory config, but revpimodio2 ignored it: see the revpi_layout finding at"
            f" {CONFIG_PATH}",
        )
    kind = KIND[signal]
    near = _candidates(rpi, kind, directions)
    if near:
        hint = f"; candidates: {', '.join(near)}"
        if any(n.endswith(".0..7") for n in near):
            hint += (
                " (a RevPi Compact or Flat carries its digital IO as whole bytes: map one bit"
                " as 'NAME.N', e.g. '" + next(n for n in near if n.endswith(".0..7"))[:-5] + ".0')"
            )
    elif kind is IoKind.AI:
        hint = "; this piCtory config has no analog input word at all: add an AIO (or MIO) module"
    else:
        hint = f"; this piCtory config has no IO of that kind at all: add a {_MODULE_FOR[kind]}"
    return error(
        "io_missing",
        path,
        f"{signal.value} is mapped to {channel!r}, but the piCtory config has no IO of that"
        f" name; it must be {_WANTED[kind]}{hint}",
    )


def _misfit(io: Any, bit: int | None, kind: IoKind, directions: tuple[int, int]) -> str | None:
    """Why this IO (or this bit of it) cannot carry a signal of this kind; None if it can."""
    real_input, real_output = directions
    is_bit = io._bitshift is not None
    bits = int(io._bitlength)
    name = io.name
    if bit is not None:
        if kind is IoKind.AI:
            return f"{name!r}.{bit} is one bit; an analog value is a whole word"
        if is_bit:
            return f"{name!r} is a single bit already: map it as {name!r}"
        if bit >= bits:
            return f"{name!r} has {bits} bits (0..{bits - 1}), so it has no bit {bit}"
    want = real_output if kind is IoKind.RO else real_input
    if io.type != want or (kind is IoKind.AI and is_bit):
        return f"{name!r} is {_describe(io, directions)}"
    if kind is IoKind.AI:
        product = product_name(_device_dict(io))
        if bits != 16:
            return f"{name!r} is {_describe(io, directions)}"
        if _product_code(io) in STATUS_MODULES:
            return f"{name!r} is a status word of module {io._parentdevice.name!r} ({product})"
        return None
    if bit is None and not is_bit:
        hint = f"map one bit of it as '{name}.N' with N = 0..{bits - 1}, e.g. '{name}.0'"
        if _product_code(io) in BYTE_IO_BASES:
            hint = (
                f"the {product_name(_device_dict(io))} carries its digital IO as whole bytes,"
                f" so the machine needs a bit IO: {hint}"
            )
        return f"{name!r} is {_describe(io, directions)}; {hint}"
    return None


def _device_dict(io: Any) -> dict[str, Any]:
    dev = io._parentdevice
    return {"productType": dev.producttype, "type": dev.type}


def _product_code(io: Any) -> int:
    return int(io._parentdevice.producttype)


def _describe(io: Any, directions: tuple[int, int]) -> str:
    real_input, real_output = directions
    where = f" of module {io._parentdevice.name!r} ({product_name(_device_dict(io))})"
    if io._bitshift is not None:
        width, unit = "a digital", ""
    else:
        bits = int(io._bitlength)
        width = f"an {bits}-bit" if bits in (8, 11, 18) else f"a {bits}-bit"
        unit = {8: " byte", 16: " word"}.get(bits, " value")
    if io.type == real_input:
        return f"{width} input{unit}{where}"
    if io.type == real_output:
        return f"{width} output{unit}{where}"
    return f"{width} memory value (a module setting){where}"


def _candidates(rpi: Any, kind: IoKind, directions: tuple[int, int]) -> list[str]:
    names: list[tuple[int, str]] = []
    for io in rpi.io:
        if _misfit(io, None, kind, directions) is None:
            analog = product_name(_device_dict(io)) in _ANALOG_FIRST
            names.append((0 if kind is IoKind.AI and analog else 1, io.name))
        elif kind is not IoKind.AI and _product_code(io) in BYTE_IO_BASES:
            whole = io._bitshift is None and int(io._bitlength) == 8
            want = directions[1] if kind is IoKind.RO else directions[0]
            status = any(word in io.name for word in _NOT_DIGITAL)
            if whole and io.type == want and not status:
                names.append((1, f"{io.name}.0..7"))
    ordered = [n for _, n in sorted(names, key=lambda p: p[0])]
    if len(ordered) > _CANDIDATES:
        return [*ordered[:_CANDIDATES], "…"]
    return ordered


def shared_output_findings(bound: list[BoundIo]) -> list[Finding]:
    """Which outputs on the relays' modules are not the machine's (a warning per module)."""
    relays = [b for b in bound if KIND[b.signal] is IoKind.RO]
    findings = []
    for dev in _unique(b.io._parentdevice for b in relays):
        mine = [b for b in relays if b.io._parentdevice is dev]
        masks: dict[int, int] = {}
        for b in mine:
            masks[b.byte] = masks.get(b.byte, 0) | b.mask
        same, other = [], []
        for io in dev.get_outputs():
            parts = [b for b in mine if b.io is io]
            if any(b.bit is None for b in parts):
                continue  # one of our bits
            if parts:
                taken = {b.bit for b in parts}
                free = [n for n in range(int(io._bitlength)) if n not in taken]
                same.append(f"bits {_bit_list(free)} of {io.name!r}")
            elif _bytes_of(io) & masks.keys():
                same.append(io.name)
            else:
                other.append(io.name)
        if not same and not other:
            continue
        ours = ", ".join(b.channel for b in mine)
        text = (
            f"module {dev.name!r} ({product_name(_device_dict(mine[0].io))}) also carries"
            " outputs the machine does not own"
        )
        if same:
            where = ", ".join(str(n) for n in sorted(masks))
            text += (
                f"; {_names(same)} share byte {where} with {ours}: the daemon changes only its"
                " own bits there (read, change, write back) and keeps theirs as it finds them"
            )
        if other:
            text += f"; it never writes {_names(other)}"
        findings.append(
            Finding(
                category="io_shared",
                severity=Severity.WARNING,
                path=f"/hal/iomap/{mine[0].signal.value}",
                message=text,
            )
        )
    return findings


def _unique(items: Any) -> list[Any]:
    out: list[Any] = []
    for item in items:
        if not any(item is seen for seen in out):
            out.append(item)
    return out


def _bytes_of(io: Any) -> set[int]:
    if io._bitshift is not None:
        return {int(io.address)}
    return set(range(int(io.address), int(io.address) + max(1, int(io._bitlength) // 8)))


def _bit_list(bits: list[int]) -> str:
    if bits and bits == list(range(bits[0], bits[-1] + 1)) and len(bits) > 2:
        return f"{bits[0]}..{bits[-1]}"
    return ", ".join(str(b) for b in bits)


def _names(names: list[str]) -> str:
    if len(names) <= _CANDIDATES:
        return ", ".join(names)
    return f"{', '.join(names[:3])}, …, {names[-1]} ({len(names)} outputs)"
