"""The Revolution Pi backend: the IO map bound to piCtory IOs through revpimodio2.

revpimodio2 reads the piCtory config and the whole process image once per cycle
(`readprocimg`, in its monitoring mode, so it never writes a byte on its own: not the base
module's RS485 limits when it opens, not a module's other outputs). The machine writes only
its own output bits, through a file descriptor of its own: a byte it shares with other outputs
is read from the image and written back with only its bits changed. The safe state (every
mapped relay off) goes through the same descriptor, so a watchdog can drop the outputs even
while revpimodio2 or the scan thread is stuck.
"""

from __future__ import annotations

import functools
import logging
import os
import stat
import threading
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import ModuleType
from typing import Any

from hal.base import HalConfigError, HalError, Inputs, Outputs
from hal.iomap import ANALOG_INPUTS, DIGITAL_INPUTS, RELAY_OUTPUTS, IoMap, Signal
from hal.pictory import (
    BYTE_IO_BASES,
    CONFIG_PATH,
    STATUS_MODULES,
    Module,
    RevPiConfigError,
    io_modules,
    layout_findings,
    product_name,
    read_config,
)
from schema.findings import Finding, Severity
from schema.io import IoKind

__all__ = ["RevPiConfigError", "RevPiHal", "check_revpi_io", "read_config"]

log = logging.getLogger("machine.hal.revpi")

KNOWN_CONFIGRSC = ("/etc/revpi/config.rsc", "/opt/KUNBUS/config.rsc")
"""Where piCtory saves its config on a device; searched when none is configured."""
PROCIMG_PATH = "/hal/revpi/procimg"
CONFIG_PROBLEMS = (KeyError, ValueError, TypeError, IndexError, AttributeError, RuntimeError)
"""What revpimodio2 raises on a config.rsc it cannot use."""

_KIND = {
    **dict.fromkeys(DIGITAL_INPUTS, IoKind.DI),
    **dict.fromkeys(ANALOG_INPUTS, IoKind.AI),
    **dict.fromkeys(RELAY_OUTPUTS, IoKind.RO),
}
_WANTED = {
    IoKind.DI: "a digital input (one bit of an input module, e.g. I_1 of a DIO)",
    IoKind.AI: "an analog input: a 16-bit input word, e.g. InputValue_1 of an AIO",
    IoKind.RO: "a digital output (one bit of an output module, e.g. O_1 of a DIO)",
}
_MODULE_FOR = {IoKind.DI: "DI or DIO module", IoKind.RO: "DO, DIO or RO module"}
_ANALOG_FIRST = frozenset({"AIO", "MIO"})
_NOT_DIGITAL = ("Status", "Temperature", "Frequency", "LED")
"""Words in the names of a Compact's or Flat's status bytes: never offered as bit IOs."""
_LOCK_WAIT_S = 0.05
"""How long a safe write waits for a scan write in progress before writing anyway."""
_CANDIDATES = 6


def raise_for_errors(findings: list[Finding]) -> None:
    """Raise `RevPiConfigError` with the error findings, if there are any."""
    errors = [f for f in findings if f.severity is Severity.ERROR]
    if errors:
        raise RevPiConfigError(errors)


def locate_configrsc(configrsc: str | None) -> str:
    """The config.rsc to use: the configured one, else the first piCtory location present."""
    if configrsc is not None:
        return configrsc
    for path in KNOWN_CONFIGRSC:
        if os.access(path, os.R_OK):
            return path
    raise RevPiConfigError(
        [
            _error(
                "revpi_config",
                CONFIG_PATH,
                f"no piCtory config found at {' or '.join(KNOWN_CONFIGRSC)};"
                " set [hal.revpi] configrsc",
            )
        ]
    )


def procimg_findings(procimg: str, need_bytes: int | None) -> list[Finding]:
    """Problems with the process image: absent, not read/writable, or too short a file."""

    def bad(why: str) -> list[Finding]:
        return [_error("revpi_procimg", PROCIMG_PATH, f"{procimg}: {why}")]

    try:
        st = os.stat(procimg)
    except OSError as exc:
        return bad(f"no process image there ({exc.strerror})")
    if not (stat.S_ISCHR(st.st_mode) or stat.S_ISREG(st.st_mode)):
        return bad("not a process image (neither the piControl device nor a file)")
    if not os.access(procimg, os.R_OK | os.W_OK):
        return bad("not readable and writable by this user")
    if need_bytes is not None and stat.S_ISREG(st.st_mode) and st.st_size < need_bytes:
        return bad(f"the file has {st.st_size} bytes; the piCtory config needs {need_bytes}")
    if need_bytes and stat.S_ISCHR(st.st_mode) and not _device_reaches(procimg, need_bytes):
        return bad(
            f"this device gives no data at byte {need_bytes - 1}, which the piCtory config"
            " needs: not the piControl device (e.g. /dev/null)?"
        )
    return []


def _device_reaches(procimg: str, need_bytes: int) -> bool:
    """Whether reading the device's byte `need_bytes - 1` gives data (seek and read, as
    revpimodio2 reads the image; nothing is written)."""
    try:
        fd = os.open(procimg, os.O_RDONLY)
    except OSError:
        return True  # permissions and the like are reported by the checks above, or at open
    try:
        os.lseek(fd, need_bytes - 1, os.SEEK_SET)
        return len(os.read(fd, 1)) == 1
    except OSError:
        return True  # a device that cannot be read this way: the open will tell
    finally:
        os.close(fd)


def import_revpimodio2() -> ModuleType:
    """revpimodio2, or a finding that says how to install it (it is an optional extra)."""
    try:
        import revpimodio2
    except ImportError as exc:
        raise RevPiConfigError(
            [
                Finding(
                    category="revpi_unavailable",
                    severity=Severity.ERROR,
                    path="/hal/backend",
                    message=f"the revpi backend needs revpimodio2 ({exc}); install it with"
                    " `pip install 'ride-machine[revpi]'`",
                )
            ]
        ) from exc
    module: ModuleType = revpimodio2
    return module


def open_modio(
    configrsc: str,
    procimg: str,
    *,
    simulator: bool = False,
    monitoring: bool = False,
) -> tuple[Any, list[Finding]]:
    """A `RevPiModIO` on these files, and its complaints about the config as warning findings.

    `configrsc` must already have passed `read_config`; anything revpimodio2 still rejects is
    turned into a `RevPiConfigError` instead of escaping as its own exception.
    """
    rp = import_revpimodio2()
    with warnings.catch_warnings(record=True) as caught:
        # Also contains revpimodio2's global `filterwarnings` call to this block.
        warnings.simplefilter("always")
        try:
            rpi = rp.RevPiModIO(
                autorefresh=False,
                monitoring=monitoring,
                syncoutputs=not monitoring,
                procimg=procimg,
                configrsc=configrsc,
                simulator=simulator,
                debug=False,
            )
        except OSError as exc:
            raise RevPiConfigError(
                [_error("revpi_procimg", PROCIMG_PATH, f"cannot open {procimg}: {exc.strerror}")]
            ) from exc
        except CONFIG_PROBLEMS as exc:
            raise RevPiConfigError(
                [
                    _error(
                        "revpi_config",
                        CONFIG_PATH,
                        f"revpimodio2 rejects {configrsc}: {type(exc).__name__} {exc}",
                    )
                ]
            ) from exc
    notes = [
        Finding(
            category="revpi_config",
            severity=Severity.WARNING,
            path=CONFIG_PATH,
            message=f"revpimodio2: {w.message}",
        )
        for w in caught
        if not issubclass(w.category, ResourceWarning)
    ]
    return rpi, notes


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
    for signal, kind in _KIND.items():
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
                _error("io_type", path, f"{signal.value} must be {_WANTED[kind]}, but {problem}")
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
        return _error(
            "io_missing",
            path,
            f"{signal.value} is mapped to {channel!r}, which is on module {mod.label} in the"
            " piCtory config, but revpimodio2 ignored it: see the revpi_layout finding at"
            f" {CONFIG_PATH}",
        )
    kind = _KIND[signal]
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
    return _error(
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
    relays = [b for b in bound if _KIND[b.signal] is IoKind.RO]
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


def check_revpi_io(iomap: IoMap, configrsc: str | None, procimg: str) -> list[Finding]:
    """Findings for the piCtory config, the process image and the IO map; never raises.

    Builds a read-only revpimodio2 view on `/dev/null`, so it neither needs nor touches the
    real process image to check the IO names.
    """
    findings = procimg_findings(procimg, need_bytes=None)
    try:
        path = locate_configrsc(configrsc)
        data = read_config(path)
    except RevPiConfigError as exc:
        return findings + exc.findings
    layout = layout_findings(data, path)
    try:
        rpi, notes = open_modio(path, os.devnull, monitoring=True)
    except RevPiConfigError as exc:
        # Our layout finding says what revpimodio2's bare exception does not.
        return findings + (layout or exc.findings)
    if layout:
        notes = _fold_layout_notes(layout, notes)
    try:
        if not findings:
            findings += procimg_findings(procimg, need_bytes=rpi.length)
        bound, problems = bind_ios(rpi, iomap, io_modules(data))
        problems += shared_output_findings(bound)
    finally:
        rpi.cleanup()
    return findings + layout + notes + problems


def _fold_layout_notes(layout: list[Finding], notes: list[Finding]) -> list[Finding]:
    """revpimodio2 warns once per ignored IO about what a layout finding already says."""
    said = ("is not in the device offset", "Offset value", "Device offset ERROR")
    ignored = [n for n in notes if any(s in n.message for s in said)]
    if not ignored:
        return notes
    rest = [n for n in notes if n not in ignored]
    count = sum("is not in the device offset" in n.message for n in ignored)
    if count:
        rest.append(
            Finding(
                category="revpi_config",
                severity=Severity.WARNING,
                path=CONFIG_PATH,
                message=f"revpimodio2 ignores {count} IO(s) that lie in the overlap above",
            )
        )
    return rest


class RevPiHal:
    """A `Hal` on a Revolution Pi process image (`/dev/piControl0`, or a file in tests).

    It writes only the mapped relay bits: a byte they share with other outputs is read from
    the image and written back with only those bits changed, and nothing else is ever written
    (no piCtory defaults, no other module). The safe state is every mapped relay off; it is
    written when the HAL opens and when it closes.
    """

    def __init__(
        self,
        iomap: IoMap,
        procimg: str,
        configrsc: str | None = None,
        *,
        hw_watchdog: bool = False,
    ) -> None:
        """`hw_watchdog`: toggle the base module's hardware watchdog bit (RevPiLED bit 7)
        from `scan_outputs`, so the box resets when the scan stops (docs/revpi.md)."""
        self.iomap = iomap
        self.procimg = procimg
        self._lock = threading.Lock()
        """Held while the scan writes outputs; a safe write waits for it only briefly."""
        self._raw_lock = threading.Lock()
        self._fd: int | None = None
        self._owned: dict[int, int] = {}
        """Byte address → the mask of our relay bits in it."""
        self._closed = False
        # Check on a read-only view first: a config that does not fit must not touch the image.
        findings = check_revpi_io(iomap, configrsc, procimg)
        raise_for_errors(findings)
        self.findings = findings
        """The warnings of the check (errors stop the constructor)."""
        for f in findings:  # `machine run` prints them; a library user finds them here too
            log.debug("event=revpi_config_warning path=%s detail=%r", f.path, f.message)
        path = locate_configrsc(configrsc)
        self.configrsc = path
        # Monitoring: revpimodio2 reads, never writes (on open it would write the base module).
        self._rpi, _ = open_modio(path, procimg, monitoring=True)
        self._wd: tuple[int, int] | None = None
        """The hardware watchdog's byte and bit mask, when asked to toggle it."""
        self._wd_next = 0.0
        self._wd_on = False
        try:
            bound, findings = bind_ios(self._rpi, iomap)
            raise_for_errors(findings)
            if hw_watchdog:
                self._wd = _watchdog_bit(self._rpi)
            self._setup(bound)
            self.force_all_outputs_safe()
        except BaseException:
            self._release()
            raise
        log.info("event=revpi_open procimg=%s configrsc=%s bytes=%d", procimg, path, len(self))

    def __len__(self) -> int:
        """Bytes of the process image the piCtory config covers."""
        return int(self._rpi.length)

    def _setup(self, bound: list[BoundIo]) -> None:
        by_kind = {k: [b for b in bound if _KIND[b.signal] is k] for k in IoKind}
        self._di = [(b.channel, b) for b in by_kind[IoKind.DI]]
        self._ai = [(b.channel, b.io) for b in by_kind[IoKind.AI]]
        self._ro = [(b.channel, b.byte, b.mask) for b in by_kind[IoKind.RO]]
        for _, byte, mask in self._ro:
            self._owned[byte] = self._owned.get(byte, 0) | mask
        self._lengths = [(dev, len(dev)) for dev in self._rpi.device]
        estop = next(b for b in bound if b.signal is Signal.ESTOP)
        self._estop_addr, self._estop_mask = estop.byte, estop.mask
        self._fd = os.open(self.procimg, os.O_RDWR)

    # -- Hal protocol -------------------------------------------------------------------
    def scan_inputs(self) -> Inputs:
        """One read of the whole process image; the E-stop comes from the same read."""
        rpi = self._live()
        try:
            ok = rpi.readprocimg()
        except (OSError, ValueError) as exc:
            raise HalError(f"cannot read the process image {self.procimg}: {exc}") from exc
        if not ok:
            raise HalError(f"cannot read the process image {self.procimg}")
        # A short read (a truncated image file) resizes revpimodio2's buffers: refuse it.
        for dev, length in self._lengths:
            if len(dev) != length:
                raise HalError(f"process image {self.procimg} is shorter than the piCtory config")
        return Inputs(
            di={ch: b.read_bool() for ch, b in self._di},
            ai={ch: int(io.value) for ch, io in self._ai},
        )

    def scan_outputs(self, outputs: Outputs) -> None:
        """Our relay bits, each byte read and written back; a channel missing is written off."""
        self._live()
        bits = dict.fromkeys(self._owned, 0)
        for ch, byte, mask in self._ro:
            if outputs.ro.get(ch, False):
                bits[byte] |= mask
        with self._lock:
            for byte, mask in self._owned.items():
                self._io(
                    functools.partial(_merge, offset=byte, mask=mask, bits=bits[byte]), "write"
                )

        if self._wd is not None:
            self._toggle_watchdog()

    def _toggle_watchdog(self) -> None:
        """Flip the hardware watchdog bit once per `WD_TOGGLE_S`, from the scan thread only:
        a scan that stops cycling stops toggling, and the hardware resets the box."""
        now = time.monotonic()
        if now < self._wd_next or self._wd is None:
            return
        self._wd_next = now + WD_TOGGLE_S
        self._wd_on = not self._wd_on
        byte, mask = self._wd
        on = mask if self._wd_on else 0
        self._io(functools.partial(_merge, offset=byte, mask=mask, bits=on), "write")

    def energised(self) -> bool:
        """Whether any of our relay bits is on in the image now (read, not remembered): what
        a supervisor asks of a stalled daemon's outputs."""
        for byte, mask in self._owned.items():
            if self._io(functools.partial(_read_byte, offset=byte), "read") & mask:
                return True
        return False

    def force_all_outputs_safe(self) -> None:
        """Our relays off through our own descriptor; works after the loop failed or close."""
        got = self._lock.acquire(timeout=_LOCK_WAIT_S)
        try:
            for byte, mask in self._owned.items():
                self._io(functools.partial(_merge, offset=byte, mask=mask, bits=0), "write")
        finally:
            if got:
                self._lock.release()

    def read_estop(self) -> bool:
        """True when the E-stop is active, read from the image now (not from the last scan)."""
        raw = self._io(lambda fd: _read_byte(fd, self._estop_addr), "read")
        level = bool(raw & self._estop_mask)
        return not level if self.iomap.estop_active_low else level

    def close(self) -> None:
        """Outputs safe, then release revpimodio2 and our descriptor; safe to call twice."""
        if self._closed:
            return
        try:
            self.force_all_outputs_safe()
        finally:
            self._release()
            log.info("event=revpi_closed procimg=%s", self.procimg)

    # -- internals ----------------------------------------------------------------------
    def _live(self) -> Any:
        if self._closed:
            raise HalError("the RevPi HAL is closed")
        return self._rpi

    def _io(self, op: Callable[[int], int], what: str) -> int:
        """Run `op` on our descriptor; on an OS error reopen the image and retry once."""
        with self._raw_lock:
            for attempt in (1, 2):
                try:
                    if self._fd is None:
                        self._fd = os.open(self.procimg, os.O_RDWR)
                    try:
                        return op(self._fd)
                    finally:
                        if self._closed:
                            self._drop_fd()  # a safe write after close() leaves nothing open
                except OSError as exc:
                    self._drop_fd()
                    if attempt == 2:
                        raise HalError(
                            f"cannot {what} the process image {self.procimg}: {exc}"
                        ) from exc
        raise AssertionError("unreachable")

    def _drop_fd(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            try:
                os.close(fd)
            except OSError as exc:
                log.warning("event=revpi_close_failed error=%r", exc)

    def _release(self) -> None:
        self._closed = True
        self._rpi.cleanup()
        with self._raw_lock:
            self._drop_fd()


WD_TOGGLE_S = 1.0
"""How often the hardware watchdog bit flips; the RevPi's MAX6370 resets after 60 s without."""


def _watchdog_bit(rpi: Any) -> tuple[int, int]:
    """The base module's watchdog bit (revpimodio2's `core.wd`: RevPiLED bit 7)."""
    wd = getattr(getattr(rpi, "core", None), "wd", None)
    if wd is None:
        raise HalConfigError(
            [
                _error(
                    "revpi_config",
                    "/hal/revpi/hw_watchdog",
                    "hw_watchdog needs a RevPi Core or Connect base module in the piCtory"
                    " config (its RevPiLED byte holds the watchdog bit); none found",
                )
            ]
        )
    return int(wd.address), int(wd._bitshift)


def _read_byte(fd: int, offset: int) -> int:
    got = os.pread(fd, 1, offset)
    if len(got) != 1:
        raise OSError(f"the image ends before byte {offset}")
    return got[0]


def _merge(fd: int, offset: int, mask: int, bits: int) -> int:
    """Set the `mask` bits of one byte to `bits`, keeping the others as the image has them.

    Written only when it changes. Between the read and the write (microseconds) another
    program's change to the same byte could be lost: `io_shared` warns where bytes are shared.
    """
    old = _read_byte(fd, offset)
    new = old & ~mask | bits
    if new != old and os.pwrite(fd, bytes([new]), offset) != 1:
        raise OSError(f"short write at byte {offset}")
    return new


def _error(category: str, path: str, message: str) -> Finding:
    return Finding(category=category, severity=Severity.ERROR, path=path, message=message)
