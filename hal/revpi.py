"""The Revolution Pi backend: the IO map bound to piCtory IOs through revpimodio2.

revpimodio2 reads the piCtory config and the whole process image once per cycle
(`readprocimg`, in its monitoring mode, so it never writes a byte on its own: not the base
module's RS485 limits when it opens, not a module's other outputs). The machine writes only
its own output bits, through a file descriptor of its own: a byte it shares with other outputs
is read from the image and written back with only its bits changed. The safe state (every
mapped relay off) goes through the same descriptor, so a watchdog can drop the outputs even
while revpimodio2 or the scan thread is stuck.

Opening revpimodio2 and checking the files: hal/revpi_open.py; binding the IO map to piCtory
IOs: hal/revpi_bind.py; the piCtory file itself: hal/pictory.py.
"""

from __future__ import annotations

import functools
import logging
import os
import threading
import time
from collections.abc import Callable
from typing import Any

from ride_machine.schema.findings import Finding, Severity
from ride_machine.schema.io import IoKind

from .base import HalConfigError, HalError, Inputs, Outputs
from .iomap import RELAY_OUTPUTS, IoMap, Signal
from .pictory import (
    CONFIG_PATH,
    RevPiConfigError,
    error,
    io_modules,
    layout_findings,
    read_config,
)
from .revpi_bind import KIND, BoundIo, bind_ios, shared_output_findings
from .revpi_open import locate_configrsc, open_modio, procimg_findings, raise_for_errors

__all__ = [
    "RevPiConfigError",
    "RevPiHal",
    "bind_ios",
    "check_revpi_io",
    "open_modio",
    "raise_for_errors",
    "read_config",
]
"""The backend, its check, and the opening and binding the simulator's image (sim/procimg.py)
shares with it."""

log = logging.getLogger("machine.hal.revpi")

_LOCK_WAIT_S = 0.05
"""How long a safe write waits for a scan write in progress before writing anyway."""


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
        by_kind = {k: [b for b in bound if KIND[b.signal] is k] for k in IoKind}
        self._di = [(b.channel, b) for b in by_kind[IoKind.DI]]
        self._ai = [(b.channel, b.io) for b in by_kind[IoKind.AI]]
        outputs = by_kind[IoKind.RO]
        self._ro = [(b.channel, b.byte, b.mask) for b in outputs if b.signal in RELAY_OUTPUTS]
        self._relay_bits: dict[int, int] = {}
        """Byte address → the mask of the ride's relays in it (what `energised` reads)."""
        for _, byte, mask in self._ro:
            self._relay_bits[byte] = self._relay_bits.get(byte, 0) | mask
        pump = [b for b in outputs if b.signal is Signal.CHARGE_PUMP]
        self._pump = (pump[0].byte, pump[0].mask) if pump else None
        """The charge pump's byte and bit: written with the relays, off in the safe state."""
        for b in outputs:
            self._owned[b.byte] = self._owned.get(b.byte, 0) | b.mask
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
        if self._pump is not None and outputs.pump:
            bits[self._pump[0]] |= self._pump[1]
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
        """Whether any of the ride's relay bits is on in the image now (read, not remembered):
        what a supervisor asks of a stalled daemon's outputs (the charge pump is no relay)."""
        for byte, mask in self._relay_bits.items():
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
                error(
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
