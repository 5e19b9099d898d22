"""The Revolution Pi backend: the IO map bound to piCtory IOs through revpimodio2.

One cycle reads the whole process image once (`readprocimg`) and writes the output modules once
(`writeprocimg`). The safe image and the E-stop bit are also reachable through a file descriptor
of our own, so a watchdog can drop the outputs even while revpimodio2 or the scan thread is stuck.
"""

from __future__ import annotations

import json
import logging
import os
import stat
import threading
import warnings
from dataclasses import dataclass
from types import ModuleType
from typing import Any

from hal.base import HalError, Inputs, Outputs
from hal.iomap import ANALOG_INPUTS, DIGITAL_INPUTS, RELAY_OUTPUTS, IoMap, Signal
from schema.findings import Finding, Severity
from schema.io import IoKind

log = logging.getLogger("machine.hal.revpi")

KNOWN_CONFIGRSC = ("/etc/revpi/config.rsc", "/opt/KUNBUS/config.rsc")
"""Where piCtory saves its config on a device; searched when none is configured."""
CONFIG_PATH = "/hal/revpi/configrsc"
PROCIMG_PATH = "/hal/revpi/procimg"
CONFIG_PROBLEMS = (KeyError, ValueError, TypeError, IndexError, AttributeError, RuntimeError)
"""What revpimodio2 raises on a config.rsc it cannot use."""
_DEVICE_KEYS = ("type", "productType", "position", "name", "offset", "inp", "out", "mem")

_KIND = {
    **dict.fromkeys(DIGITAL_INPUTS, IoKind.DI),
    **dict.fromkeys(ANALOG_INPUTS, IoKind.AI),
    **dict.fromkeys(RELAY_OUTPUTS, IoKind.RO),
}
_WANTED = {
    IoKind.DI: "a digital input (one bit of an input module)",
    IoKind.AI: "an analog input (a 16-bit input word, e.g. InputValue_1 of an AIO)",
    IoKind.RO: "a digital output (one bit of an output module, e.g. O_1 of a DIO)",
}
_LOCK_WAIT_S = 0.05
"""How long a safe write waits for a scan write in progress before writing anyway."""
_CANDIDATES = 6


class RevPiConfigError(HalError):
    """The piCtory config, the process image or the IO map does not fit; see `findings`."""

    def __init__(self, findings: list[Finding]) -> None:
        self.findings = findings
        super().__init__("; ".join(f"{f.path}: {f.message}" for f in findings))


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


def read_config(path: str) -> dict[str, Any]:
    """The parsed config.rsc, checked for the shape revpimodio2 relies on."""

    def bad(why: str) -> RevPiConfigError:
        return RevPiConfigError([_error("revpi_config", CONFIG_PATH, f"{path}: {why}")])

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
    return []


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
                [_error("revpi_config", CONFIG_PATH, f"revpimodio2 rejects {configrsc}: {exc}")]
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
    """A logical signal and the revpimodio2 IO object it resolved to."""

    signal: Signal
    channel: str
    io: Any


def bind_ios(rpi: Any, iomap: IoMap) -> tuple[list[BoundIo], list[Finding]]:
    """Resolve every signal of the IO map to a piCtory IO of the right kind.

    In simulator mode revpimodio2 swaps inputs and outputs, so the kinds are checked as the
    real device sees them.
    """
    rp = import_revpimodio2()
    from revpimodio2.io import IOBase

    real_input, real_output = (rp.OUT, rp.INP) if rpi.simulator else (rp.INP, rp.OUT)
    bound: list[BoundIo] = []
    findings: list[Finding] = []
    for signal, kind in _KIND.items():
        channel = iomap.channel(signal)
        path = f"/hal/iomap/{signal.value}"
        io = getattr(rpi.io, channel, None)  # IOList has no .get; names are attributes
        if not isinstance(io, IOBase):
            near = _candidates(rpi, kind, real_input, real_output)
            findings.append(
                _error(
                    "io_missing",
                    path,
                    f"{signal.value} is mapped to {channel!r}, but the piCtory config has no IO"
                    f" of that name; it must be {_WANTED[kind]}"
                    + (f"; candidates: {', '.join(near)}" if near else ""),
                )
            )
            continue
        actual = _kind_of(io, real_input, real_output)
        if actual is not kind:
            findings.append(
                _error(
                    "io_type",
                    path,
                    f"{signal.value} must be {_WANTED[kind]}, but {channel!r} is"
                    f" {_describe(io, real_input, real_output)}",
                )
            )
            continue
        if kind is IoKind.RO and io.defaultvalue:
            findings.append(
                Finding(
                    category="io_default",
                    severity=Severity.WARNING,
                    path=path,
                    message=f"{channel!r} has default value 1 in piCtory, so piControl switches"
                    " it on before the daemon runs; set its default to 0",
                )
            )
        bound.append(BoundIo(signal, channel, io))
    return bound, findings


def check_revpi_io(iomap: IoMap, configrsc: str | None, procimg: str) -> list[Finding]:
    """Findings for the piCtory config, the process image and the IO map; never raises.

    Builds a read-only revpimodio2 view on `/dev/null`, so it neither needs nor touches the
    real process image to check the IO names.
    """
    findings = procimg_findings(procimg, need_bytes=None)
    try:
        path = locate_configrsc(configrsc)
        read_config(path)
        rpi, notes = open_modio(path, os.devnull, monitoring=True)
    except RevPiConfigError as exc:
        return findings + exc.findings
    try:
        if not findings:
            findings += procimg_findings(procimg, need_bytes=rpi.length)
        _, problems = bind_ios(rpi, iomap)
    finally:
        rpi.cleanup()
    return findings + notes + problems


class RevPiHal:
    """A `Hal` on a Revolution Pi process image (`/dev/piControl0`, or a file in tests).

    Outputs are forced safe when it opens and when it closes. The safe image is every output
    of the modules we drive at its piCtory default, with every mapped relay off.
    """

    def __init__(self, iomap: IoMap, procimg: str, configrsc: str | None = None) -> None:
        self.iomap = iomap
        self.procimg = procimg
        self._lock = threading.Lock()
        """Held while the scan writes outputs; a safe write waits for it only briefly."""
        self._raw_lock = threading.Lock()
        self._fd: int | None = None
        self._safe: list[tuple[int, bytes]] = []
        self._closed = False
        # Check on a read-only view first: a config that does not fit must not touch the image.
        findings = check_revpi_io(iomap, configrsc, procimg)
        raise_for_errors(findings)
        for f in findings:
            log.warning("event=revpi_config_warning path=%s detail=%r", f.path, f.message)
        path = locate_configrsc(configrsc)
        self.configrsc = path
        self._rpi, _ = open_modio(path, procimg)
        try:
            bound, findings = bind_ios(self._rpi, iomap)
            raise_for_errors(findings)
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
        rpi = self._rpi
        by_kind = {k: [(b.channel, b.io) for b in bound if _KIND[b.signal] is k] for k in IoKind}
        self._di = by_kind[IoKind.DI]
        self._ai = by_kind[IoKind.AI]
        self._ro = by_kind[IoKind.RO]
        # Only the modules carrying our relays are written: other modules' outputs stay theirs.
        self._out_devices = _owners(rpi, [io for _, io in self._ro])
        self._lengths = [(dev, len(dev)) for dev in rpi.device]
        for dev in self._out_devices:
            rpi.setdefaultvalues(dev)
            for _, io in self._ro:
                if io in dev:
                    io.value = False
            start, end = _output_span(dev)
            self._safe.append((start, bytes(dev)[start - dev.offset : end - dev.offset]))
        estop = rpi.io[self.iomap.estop]
        self._estop_addr = int(estop.address)
        # The IOs at a byte address are listed by bit, which gives the E-stop's bit.
        self._estop_mask = 1 << rpi.io[estop.address].index(estop)
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
            di={ch: bool(io.value) for ch, io in self._di},
            ai={ch: int(io.value) for ch, io in self._ai},
        )

    def scan_outputs(self, outputs: Outputs) -> None:
        """One write per output module; a channel missing from `outputs` is written off."""
        rpi = self._live()
        with self._lock:
            for ch, io in self._ro:
                io.value = bool(outputs.ro.get(ch, False))
            try:
                # A list, not a generator: every module is written even if one fails.
                ok = all([rpi.writeprocimg(dev) for dev in self._out_devices])
            except (OSError, ValueError) as exc:
                raise HalError(f"cannot write the process image {self.procimg}: {exc}") from exc
            if not ok:
                raise HalError(f"cannot write the process image {self.procimg}")

    def force_all_outputs_safe(self) -> None:
        """Write the safe image through our own descriptor; works after the loop or close."""
        got = self._lock.acquire(timeout=_LOCK_WAIT_S)
        try:
            for start, data in self._safe:
                self._raw(start, data)
        finally:
            if got:
                self._lock.release()

    def read_estop(self) -> bool:
        """True when the E-stop is active, read from the image now (not from the last scan)."""
        level = bool(self._raw(self._estop_addr, None)[0] & self._estop_mask)
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

    def _raw(self, offset: int, data: bytes | None) -> bytes:
        """Write `data` at `offset`, or read the byte there; on an error reopen and retry once."""
        with self._raw_lock:
            for attempt in (1, 2):
                try:
                    if self._fd is None:
                        self._fd = os.open(self.procimg, os.O_RDWR)
                    try:
                        return _pio(self._fd, offset, data)
                    finally:
                        if self._closed:
                            self._drop_fd()  # a safe write after close() leaves nothing open
                except OSError as exc:
                    self._drop_fd()
                    if attempt == 2:
                        raise HalError(f"process image {self.procimg}: {exc}") from exc
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


def _pio(fd: int, offset: int, data: bytes | None) -> bytes:
    """Seek and write `data` (or read one byte): what revpimodio2 does, on our descriptor."""
    os.lseek(fd, offset, os.SEEK_SET)
    if data is None:
        got = os.read(fd, 1)
        if len(got) != 1:
            raise OSError(f"the image ends before byte {offset}")
        return got
    if os.write(fd, data) != len(data):
        raise OSError(f"short write at byte {offset}")
    return data


def _kind_of(io: Any, real_input: int, real_output: int) -> IoKind | None:
    bit = isinstance(io.value, bool)
    if io.type == real_input:
        return IoKind.DI if bit else IoKind.AI
    if io.type == real_output and bit:
        return IoKind.RO
    return None


def _describe(io: Any, real_input: int, real_output: int) -> str:
    width = "a digital" if isinstance(io.value, bool) else f"a {8 * io.length}-bit"
    if io.type == real_input:
        return f"{width} input"
    if io.type == real_output:
        return f"{width} output"
    return f"{width} memory value (a module setting)"


def _candidates(rpi: Any, kind: IoKind, real_input: int, real_output: int) -> list[str]:
    names = [io.name for io in rpi.io if _kind_of(io, real_input, real_output) is kind]
    if len(names) > _CANDIDATES:
        return [*names[:_CANDIDATES], "…"]
    return names


def _owners(rpi: Any, ios: list[Any]) -> list[Any]:
    """The devices holding these IOs, in process-image order, each once."""
    return [dev for dev in rpi.device if any(io in dev for io in ios)]


def _output_span(dev: Any) -> tuple[int, int]:
    """The absolute byte range of a device's outputs: what `writeprocimg(dev)` writes."""
    outs = dev.get_outputs()
    start = min(io.address for io in outs)
    end = max(io.address + (1 if isinstance(io.value, bool) else io.length) for io in outs)
    return start, end


def _error(category: str, path: str, message: str) -> Finding:
    return Finding(category=category, severity=Severity.ERROR, path=path, message=message)
