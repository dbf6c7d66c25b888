"""One pysoem master on one interface: bring-up, the cyclic frame, states, SDOs, shutdown.

Only blocking work lives here; :mod:`.driver` decides when it runs (a dedicated thread for
bring-up, SDOs and shutdown; the tick for the cyclic frame). A SOEM context is used by at most
one thread at a time for the same kind of traffic: the cyclic frame from the tick (or the
keep-alive thread before the first tick), mailbox traffic from the bus thread. SOEM matches
replies by datagram index, so the two may overlap.

pysoem releases the GIL only in ``config_init``, the process-data calls and SDOs (we always
ask it to). ``config_map``, ``config_dc``, ``read_state``, ``write_state``, ``state_check``,
``recover`` and ``reconfig`` hold it: while they run, no other Python thread runs, the event
loop included. They are used at bring-up, shutdown and after a bus error only.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import logging
import os
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aiohal.errors import AiohalError
from aiohal.fieldbus.busvar import LayoutError, PdoLayout, names_for

from . import sii as sii_layout
from . import sm_watchdog
from .names import KNOWN_DEVICES

log = logging.getLogger(__name__)

INIT, PREOP, BOOT, SAFEOP, OP = 0x01, 0x02, 0x03, 0x04, 0x08
STATE_ERROR, STATE_ACK = 0x10, 0x10
IDENTITY_READS = 3  # bus scans at most, while a slave's vendor id or product code reads as zero
AL_STATUS_REGISTER = 0x0130  # AL status (state, error bit), then 0x0134: the AL status code
STATE_READ_TIMEOUT_US = 2000  # one slave's checked state read
_STATE_NAMES = {0: "NONE", INIT: "INIT", PREOP: "PREOP", BOOT: "BOOT", SAFEOP: "SAFEOP", OP: "OP"}
#: where the lock files that keep a second master off an interface live (one per interface)
LOCK_DIR = Path(os.environ.get("AIOHAL_LOCK_DIR", "/run/lock"))


class EthercatError(AiohalError, RuntimeError):
    """Base of the EtherCAT driver's errors."""


class BringUpError(EthercatError):
    """The bus did not come up as configured; the message names the slave and the reason."""


class TransientBringUpError(BringUpError):
    """The bus did not answer in time (a frame lost, a wait run out: a stall of the host does
    that): a fresh bring-up may get through, where a configuration error would fail again."""


class SlaveDataError(BringUpError):
    """A value read from a slave does not fit what it stands for (too short, out of range);
    the message names the slave and the object."""


class SdoAbortError(EthercatError):
    """An SDO transfer was aborted by the slave (``abort_code``) or failed in the mailbox."""

    def __init__(self, where: str, abort_code: int | None, reason: str) -> None:
        self.abort_code = abort_code
        code = f" abort 0x{abort_code:08X}" if abort_code is not None else ""
        super().__init__(f"{where}:{code} {reason}")


def state_name(state: int) -> str:
    name = _STATE_NAMES.get(state & 0x0F, f"0x{state & 0x0F:X}")
    return name + ("+ERROR" if state & STATE_ERROR else "")


def shares_a_byte(layout: PdoLayout) -> bool:
    """A slave of 1-7 bits in a direction: SOEM packs it into a byte it shares with its
    neighbours, and pysoem reads and writes whole bytes per slave, so this driver refuses it."""
    return 0 < layout.output_bits < 8 or 0 < layout.input_bits < 8


@dataclass
class SlaveInfo:
    """What bring-up found at one bus position."""

    position: int
    name: str  # the configured name (bus variables are "<name>.<variable>")
    device_name: str  # what the slave calls itself (SII string 1)
    vendor_id: int
    product_code: int
    revision: int
    layout: PdoLayout
    output_bytes: int
    input_bytes: int

    @property
    def wkc(self) -> int:
        """This slave's share of the process-data working counter: +2 outputs written, +1 inputs read."""
        return 2 * (self.output_bytes > 0) + (self.input_bytes > 0)


class Bus:
    """A pysoem ``Master`` opened on exactly one named interface."""

    def __init__(self, pysoem: Any, ifname: str, *, overlap: bool = False, take_over: bool = False) -> None:
        self.pysoem = pysoem
        self.ifname = ifname
        self.overlap = overlap
        self.take_over = take_over  # bring up a bus whose slaves another master runs in OP
        self._lock_fd: int | None = None
        self._lock_path = LOCK_DIR
        self.sii_mapped: set[int] = set()  # CoE slaves without 0x1C12/0x1C13: PDOs from their SII
        self.master: Any = None
        self.slaves: list[Any] = []  # pysoem slave objects, made once (each access makes a new one)
        #: pysoem's errors for a mailbox or datagram frame that did not come back (not a refusal)
        self.lost_frame = (pysoem.MailboxError, pysoem.PacketError, pysoem.WkcError)
        self.is_open = False
        #: the AL states are read from the tick (after a bus error) and off it (the periodic
        #: check): one at a time, so that a read never sees another's half-written states
        self._states_lock = threading.Lock()

    # ------------------------------------------------------------ bring-up

    def open(self) -> int:
        """Open the interface and find the slaves; their number."""
        try:
            socket.if_nametoindex(self.ifname)
        except OSError:
            raise BringUpError(f"network interface {self.ifname!r} does not exist (options.interface)") from None
        self._hold_interface()
        self.master = self.pysoem.Master()
        try:
            self.master.open(self.ifname)
        except Exception as exc:  # pysoem raises ConnectionError without root or CAP_NET_RAW
            self._release_interface()
            raise BringUpError(f"cannot open {self.ifname!r} for EtherCAT (root or CAP_NET_RAW needed): {exc}") from exc
        self.is_open = True
        self._refuse_a_running_bus()
        for attempt in range(1, IDENTITY_READS + 1):
            found = self.master.config_init(release_gil=True)
            if found < 0:
                raise TransientBringUpError(
                    f"no EtherCAT frame came back on {self.ifname!r}: nothing connected, or the link is down"
                )
            self.slaves = list(self.master.slaves)
            # vendor id 0 is no vendor's, and no product is numbered 0 in practice: SOEM reads a
            # zero when an EEPROM read does not finish in time (a stall of the host), so the bus
            # is scanned again
            unread = [i for i, slave in enumerate(self.slaves) if slave.man == 0 or slave.id == 0]
            if not unread or attempt == IDENTITY_READS:
                break
            log.warning(
                "ethercat %s: the identity of slave(s) %s read as zero; scanning the bus again (%d of %d)",
                self.ifname,
                ", ".join(map(str, unread)),
                attempt + 1,
                IDENTITY_READS,
            )
        return len(self.slaves)

    def _hold_interface(self) -> None:
        """An exclusive lock on the interface for as long as the bus is open: a second master
        on it would reset every slave (``config_init``) under the first one's feet. The lock
        file is removed when the bus closes; a lock taken on a file another process removed
        meanwhile is no lock, so the file locked must still be the one at the path."""
        path = LOCK_DIR / f"aiohal-ethercat-{self.ifname}.lock"
        for _ in range(5):  # bounded: a file removed between open and lock is opened again
            try:
                fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:
                raise BringUpError(
                    f"cannot create the interface lock {path} ({exc}); AIOHAL_LOCK_DIR names another directory"
                ) from exc
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
                os.close(fd)
                raise BringUpError(
                    f"interface {self.ifname!r} is held by another aiohal process (pid {holder}, lock "
                    f"{path}): a second master would knock it off the bus; stop that one first"
                ) from None
            if _same_file(fd, path):
                break
            os.close(fd)
        else:
            raise BringUpError(f"the interface lock {path} keeps being removed: another program is at it")
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._lock_fd = fd
        self._lock_path = path

    def _release_interface(self) -> None:
        fd, self._lock_fd = self._lock_fd, None
        if fd is not None:
            with contextlib.suppress(OSError):  # removed while still held: nobody else can hold it now
                if _same_file(fd, self._lock_path):
                    os.unlink(self._lock_path)
            os.close(fd)  # (releases the lock)

    def _refuse_a_running_bus(self) -> None:
        """Before anything is written: a slave in OP means another master runs this bus (one
        that is not aiohal, or on another host). SOEM's state check of "slave 0" before
        ``config_init`` is one broadcast read of the AL status, whose data is the OR of every
        slave's state: the OP bit is there if any slave is in OP."""
        if self.take_over:
            return
        # Three reads: SOEM takes any frame on the interface whose index matches the one it
        # waits for, and another master's frames are there too, so one read may be another's
        # frame. 0 is no state (no reply in time, a busy host): asked again, five reads at most.
        seen, answered = 0, 0
        for _ in range(5):
            state = self.master.state_check(OP, 2000)
            seen |= state
            answered += state != 0
            if seen & OP or answered == 3:
                break
        if seen & OP:
            self.close()
            raise BringUpError(
                f"slaves on {self.ifname!r} are in OP (AL states ORed: 0x{seen:02X}): another master "
                "is running this bus, and bringing it up would knock that one off; stop it, or set "
                "options.take_over = true"
            )

    def read_layout(self, position: int, names_overrides: dict | None = None) -> PdoLayout:
        """The slave's PDO layout, named from its name table; in PREOP, before the master maps
        it. From its CoE PDO assignment (0x1C12/0x1C13 and the mapping objects), or from its
        SII PDO categories for a slave without CoE (as SOEM maps it)."""
        slave = self.slaves[position]
        where = f"slave {position} ({slave.name})"
        sii = self.sii(position)
        if not sii_layout.has_coe(sii):
            rx, tx = sii_layout.read_pdos(sii)
            # device type 0: no object 0x1000 to say CiA 402, so no drive names are assumed
            names = names_for(slave.man, slave.id, device_type=0, overrides=names_overrides, known=KNOWN_DEVICES)
            return PdoLayout.from_sii(rx, tx, names)
        names = names_for(
            slave.man, slave.id, device_type=self.device_type(position), overrides=names_overrides, known=KNOWN_DEVICES
        )
        try:
            rx_assign = self._assignment(slave, where, 0x1C12)
            tx_assign = self._assignment(slave, where, 0x1C13)
            mappings = {pdo: self._mapping(slave, where, pdo) for pdo in (*rx_assign, *tx_assign)}
        except self.pysoem.SdoError as exc:
            if exc.abort_code == ABORT_NO_OBJECT:
                # no 0x1C12/0x1C13: SOEM then maps the PDOs its SII describes, and so do we
                rx, tx = sii_layout.read_pdos(sii)
                if rx or tx:
                    self.sii_mapped.add(position)
                    log.info(
                        "ethercat %s: %s has no PDO assignment object (0x1C12/0x1C13); its PDOs are read from its SII",
                        self.ifname,
                        where,
                    )
                    return PdoLayout.from_sii(rx, tx, names)
            raise LayoutError(
                f"{where}: reading its PDO mapping failed: abort 0x{exc.abort_code:08X} {exc.desc}"
            ) from exc
        except self.lost_frame as exc:
            raise TransientBringUpError(
                f"{where}: reading its PDO mapping failed ({type(exc).__name__}: {exc})"
            ) from exc
        try:
            return PdoLayout.from_coe(rx_assign, tx_assign, mappings, names)
        except LayoutError as exc:
            raise LayoutError(f"{where}: {exc}") from exc

    def device_type(self, position: int) -> int | None:
        """Object 0x1000 of a slave with CoE (its profile in the low 16 bits, 402 for a drive),
        or None when it does not answer it."""
        try:
            data = self.slaves[position].sdo_read(0x1000, 0, release_gil=True)
        except Exception:  # optional to answer: the name table then falls back to CiA 402's
            return None
        return struct.unpack_from("<I", data)[0] if len(data) >= 4 else None

    def sii(self, position: int) -> sii_layout.SiiReader:
        """The slave's SII EEPROM, read on demand (blocking; each read is a few frames)."""
        slave = self.slaves[position]

        def read(word: int) -> bytes:
            try:
                return slave.eeprom_read(word)
            except Exception as exc:
                raise TransientBringUpError(
                    f"slave {position} ({slave.name}): reading SII word 0x{word:04X} failed "
                    f"({type(exc).__name__}: {exc})"
                ) from exc

        return sii_layout.SiiReader(read)

    def _sdo_retried(self, slave: Any, index: int, subindex: int, size: int = 0) -> bytes:
        """An SDO read, tried again when its mailbox frame was lost: a read changes nothing."""
        return self._again_if_lost(
            lambda: slave.sdo_read(index, subindex, size, release_gil=True),
            f"SDO read 0x{index:04X}:{subindex:02X} of {slave.name}",
        )

    def _sdo_write_again_if_lost(self, slave: Any, index: int, subindex: int, data: bytes) -> None:
        """An SDO write of a value, tried again when its mailbox frame was lost. Only for writes
        that set a value, where a second one changes nothing if the first got through (the PDO
        mapping at bring-up); not for commands."""
        self._again_if_lost(
            lambda: slave.sdo_write(index, subindex, data, release_gil=True),
            f"SDO write 0x{index:04X}:{subindex:02X} to {slave.name}",
        )

    def _again_if_lost(self, transfer: Any, what: str, attempts: int = 3) -> Any:
        """``transfer()``, tried again when its frame was lost (not when the slave refused it):
        a lost frame is a normal event on a bus, and on a busy host."""
        for attempt in range(attempts - 1):
            try:
                return transfer()
            except self.lost_frame:
                time.sleep(0.01 * (attempt + 1))
                log.info("ethercat %s: %s lost, trying again", self.ifname, what)
        return transfer()

    def write_pdo_assignment(self, position: int, assign: int, pdos: list[tuple[int, list[int]]]) -> None:
        """Assign ``pdos`` (0x1C12: outputs, 0x1C13: inputs), in order, writing the mapping of
        each PDO given entries (CiA 301's sequence: count 0, entries, count); in PREOP."""
        slave = self.slaves[position]
        if not sii_layout.has_coe(self.sii(position)):
            raise LayoutError(
                f"slave {position} ({slave.name}) has no CoE: its PDOs are fixed in its SII and "
                "cannot be remapped (leave out its rx_pdos / tx_pdos)"
            )

        def write(index: int, subindex: int, data: bytes) -> None:
            with self._sdo_errors(
                f"slave {position} ({slave.name}): PDO remapping, SDO write 0x{index:04X}:{subindex:02X}"
            ):
                self._sdo_write_again_if_lost(slave, index, subindex, data)

        # what the slave has now, to put back if it refuses the new mapping half-way: a slave
        # left with 0x1C12:00 = 0 refuses SAFEOP (AL status 0x001D) until it is power-cycled
        where = f"slave {position} ({slave.name})"
        try:
            before = self._assignment(slave, where, assign)
            before_maps = {pdo: self._mapping(slave, where, pdo) for pdo, entries in pdos if entries}
        except Exception as exc:
            before, before_maps = None, {}
            log.info("ethercat %s: %s: its PDO mapping could not be read before remapping: %s", self.ifname, where, exc)
        try:
            _write_assignment(write, assign, pdos)
        except Exception as exc:
            if before is None:
                raise BringUpError(
                    f"{exc}; the slave's previous mapping was not readable, so it was not restored: it may "
                    "refuse SAFEOP until it is power-cycled"
                ) from exc
            try:
                old = {pdo: before_maps.get(pdo, []) for pdo in before}
                _write_assignment(
                    write,
                    assign,
                    [(pdo, before_maps.get(pdo, [])) for pdo, _ in pdos if pdo not in old] + list(old.items()),
                    count=len(before),
                )
            except Exception as undo:
                raise BringUpError(
                    f"{exc}; putting its previous mapping back failed too ({undo}): it is left half-mapped "
                    "and may refuse SAFEOP (AL status 0x001D) until it is power-cycled"
                ) from exc
            raise BringUpError(f"{exc}; the slave refused this mapping, and its previous one is restored") from exc
        log.info(
            "ethercat %s: slave %d (%s) 0x%04X = %s",
            self.ifname,
            position,
            slave.name,
            assign,
            ", ".join(f"0x{pdo:04X}" for pdo, _ in pdos),
        )

    def _assignment(self, slave: Any, where: str, index: int) -> list[int]:
        """A PDO assignment (0x1C12 outputs, 0x1C13 inputs): the PDO mapping objects, in order."""
        count = sdo_count(where, index, self._sdo_retried(slave, index, 0))
        return [pdo_index(where, index, sub, self._sdo_retried(slave, index, sub)) for sub in range(1, count + 1)]

    def _mapping(self, slave: Any, where: str, index: int) -> list[int]:
        """A PDO's mapping entries (index << 16 | subindex << 8 | bits)."""
        count = sdo_count(where, index, self._sdo_retried(slave, index, 0))
        return [mapping_entry(where, index, sub, self._sdo_retried(slave, index, sub)) for sub in range(1, count + 1)]

    def map(
        self,
        dc: bool,
        sync0: Sequence[int] = (),
        cycle_ns: int = 0,
        shift_ns: int = 0,
        safeop_timeout_s: float = 2.0,
        static_frames: int = 0,
    ) -> int:
        """Map the process data (the masters's IO map), set DC up (``static_frames`` of static
        drift compensation, SYNC0 on the slaves at ``sync0``), reach SAFEOP; the map's size."""
        size = 0
        try:
            size = self.master.config_overlap_map() if self.overlap else self.master.config_map()
        except self.pysoem.ConfigMapError as exc:
            errors = list(getattr(exc, "error_list", []))
            if not errors or not all(self._missing_assignment(e) for e in errors):
                aborts = all(isinstance(e, self.pysoem.SdoError) for e in errors)
                error = BringUpError if errors and aborts else TransientBringUpError  # (aborts come again)
                raise error(f"mapping process data failed: {exc}") from exc
            # SOEM logs the aborts of the slaves without 0x1C12/0x1C13 and maps them from their
            # SII; pysoem raises them after the map is complete. Their sizes are checked below.
            log.info(
                "ethercat %s: mapped slave(s) %s from the SII",
                self.ifname,
                ", ".join(sorted({str(e.slave_pos - 1) for e in errors})),
            )
        if dc:
            self.master.config_dc()
            self._compensate_drift(static_frames)
            for position in sync0:
                self._activate_sync0(position, cycle_ns, shift_ns)
        if not reach_safeop(self.master, safeop_timeout_s):
            error = BringUpError if in_error(self.slaves) else TransientBringUpError
            raise error(f"slaves did not reach SAFEOP within {safeop_timeout_s:g} s: " + self.describe_not_in(SAFEOP))
        return size

    def _compensate_drift(self, frames: int) -> None:
        """Static drift compensation: SOEM's process-data frame carries an FRMW of the reference
        clock's system time once config_dc found DC slaves, and each slave after the reference
        takes it into its time control loop; ``frames`` of them back to back lock the slaves'
        clocks before SYNC0 starts (outputs are not applied before SAFEOP)."""
        send, receive = self.cyclic_calls(self.pysoem.settings.timeouts.ret)
        for _ in range(frames):
            send()
            receive()

    def _missing_assignment(self, error: Any) -> bool:
        """A ConfigMapError item that is SOEM finding no 0x1C12/0x1C13 on a slave whose PDOs
        this bus read from its SII (SOEM's ``slave_pos`` counts from 1)."""
        return (
            isinstance(error, self.pysoem.SdoError)
            and error.abort_code == ABORT_NO_OBJECT
            and error.index in (0x1C12, 0x1C13)
            and error.slave_pos - 1 in self.sii_mapped
        )

    def _activate_sync0(self, position: int, cycle_ns: int, shift_ns: int) -> None:
        """SYNC0 every ``cycle_ns`` (SOEM starts it about 100 ms ahead), read back: pysoem's
        dc_sync reports nothing, and a slave without DC ignores the registers."""
        slave = self.slaves[position]
        slave.dc_sync(True, cycle_ns, shift_ns)
        timeout = self.pysoem.settings.timeouts.ret
        try:
            active = slave._fprd(0x0981, 1, timeout_us=timeout)[0] & 0x03 == 0x03
            cycle = struct.unpack("<I", slave._fprd(0x09A0, 4, timeout_us=timeout))[0]
        except self.pysoem.WkcError:
            active, cycle = False, 0
        if not active or cycle != cycle_ns:
            raise BringUpError(
                f"slave {position} ({slave.name}) did not take SYNC0 at {cycle_ns} ns (no distributed "
                f"clock?); options.slaves[{position}].sync0 = false leaves it out"
            )

    def program_pd_watchdog(self, position: int, ms: float) -> sm_watchdog.Setting:
        """Write the slave's process-data watchdog time (:func:`.sm_watchdog.program`): in
        SAFEOP, before OP. What it holds afterwards, read back."""
        slave = self.slaves[position]
        where = f"slave {position} ({slave.name})"
        read, write = self._registers(slave, where)
        try:
            return sm_watchdog.program(read, write, ms, where)
        except ValueError as exc:
            raise BringUpError(f"{exc}; options.sm_watchdog_ms = 0 leaves every slave's own setting") from None

    def check_pd_watchdog(self, position: int, written: sm_watchdog.Setting) -> sm_watchdog.Setting:
        """After OP: the slave still holds the watchdog time written and watches its output
        SyncManager, or a :class:`BringUpError` names it with what it holds."""
        slave = self.slaves[position]
        where = f"slave {position} ({slave.name})"
        read, _ = self._registers(slave, where)
        setting = sm_watchdog.read_setting(read)
        why = sm_watchdog.check(setting, written, where)
        if why is not None:
            raise BringUpError(
                f"{why}: it would keep driving when this process stops; options.sm_watchdog_ms = 0 "
                "accepts that (no slave's watchdog is then set or checked)"
            )
        return setting

    def _registers(self, slave: Any, where: str) -> tuple[sm_watchdog.Read, sm_watchdog.Write]:
        """Register reads and writes of one slave (FPRD/FPWR); a frame lost is a
        :class:`TransientBringUpError`."""
        timeout = self.pysoem.settings.timeouts.ret

        def read(address: int, size: int) -> bytes:
            try:
                return bytes(slave._fprd(address, size, timeout_us=timeout))
            except self.lost_frame as exc:
                raise TransientBringUpError(f"{where}: reading register 0x{address:04X} failed ({exc})") from exc

        def write(address: int, data: bytes) -> None:
            try:
                slave._fpwr(address, data, timeout_us=timeout)
            except self.lost_frame as exc:
                raise TransientBringUpError(f"{where}: writing register 0x{address:04X} failed ({exc})") from exc

        return read, write

    def request_op(self, exchange: Any, timeout_s: float, period_s: float, again_s: float = 0.1) -> None:
        """SAFEOP → OP (:func:`reach_op`), or a :class:`BringUpError` naming the slaves short of it."""
        if not reach_op(self.master, exchange, timeout_s, period_s, again_s):
            if in_error(self.slaves):
                raise BringUpError("slaves did not reach OP: " + self.describe_not_in(OP))
            raise TransientBringUpError(f"slaves did not reach OP within {timeout_s:g} s: " + self.describe_not_in(OP))

    def describe_not_in(self, state: int) -> str:
        """The slaves not in ``state`` with their state and AL status code (after read_state)."""
        bad = []
        for i, s in enumerate(self.slaves):
            if s.state != state:
                code = s.al_status
                bad.append(
                    f"slave {i} ({s.name}) in {state_name(s.state)}, AL status 0x{code:04X} "
                    f"({self.pysoem.al_status_code_to_string(code)})"
                )
        return "; ".join(bad) or "(all there now)"

    # ------------------------------------------------------------ the cyclic frame

    def send(self) -> None:
        if self.overlap:
            self.master.send_overlap_processdata(release_gil=True)
        else:
            self.master.send_processdata(release_gil=True)

    def receive(self, timeout_us: int) -> int:
        return self.master.receive_processdata(timeout_us, release_gil=True)

    def cyclic_calls(self, timeout_us: int) -> tuple[Callable[[], Any], Callable[[], int]]:
        """``send()`` and ``receive()`` for the tick, bound to pysoem once: on a tick that starts
        on cold caches, each Python frame between the loop and pysoem costs more than the call."""
        send = self.master.send_overlap_processdata if self.overlap else self.master.send_processdata
        return (
            functools.partial(send, release_gil=True),
            functools.partial(self.master.receive_processdata, timeout_us, release_gil=True),
        )

    # ------------------------------------------------------------ after a bus error

    def states(self) -> list[int]:
        """Every slave's AL state, read now (holds the GIL for a frame or two)."""
        with self._states_lock:
            self.master.read_state()
            return [s.state for s in self.slaves]

    def checked_states(self, positions: Sequence[int], until_silent: bool = False) -> dict[int, tuple[int, int] | None]:
        """The AL state and AL status code of the slaves at ``positions``, each slave read by a
        frame of its own whose working counter pysoem checks (WkcError otherwise); None for a
        slave that did not answer in ``STATE_READ_TIMEOUT_US``. ``states()`` (SOEM's
        read_state) reads the slaves in one frame and, when no reply comes or another frame's
        reply stands in for it (SOEM matches a reply by its index, and indices are reused: a
        reply late from a stalled host, a second master's frames), fills the states from
        whatever its buffer held: the bytes of another frame, the same ones read after read.
        Holds the GIL for a round trip a slave, and a timeout a silent one; ``until_silent``:
        the first silent slave ends the reads (those after it are left out)."""
        found: dict[int, tuple[int, int] | None] = {}
        with self._states_lock:
            for position in positions:
                try:
                    raw = bytes(self.slaves[position]._fprd(AL_STATUS_REGISTER, 6, timeout_us=STATE_READ_TIMEOUT_US))
                except Exception:  # pysoem's WkcError: the frame came back unanswered, or not at all
                    found[position] = None
                    if until_silent:
                        break
                    continue
                state, code = struct.unpack_from("<H2xH", raw)
                found[position] = (state & 0x1F, code)
        return found

    def recover_steps(self, positions: Sequence[int]) -> dict[int, tuple[int, int] | None]:
        """One quick step toward OP for each slave at ``positions`` (those that dropped out):
        acknowledge an error, or SAFEOP → OP (a checked state read, then one frame a slave).
        A slave below SAFEOP (gone, or back after losing power) would need SOEM's reconfig /
        recover, which wait up to seconds holding the GIL: that is not done here. Returns
        what the read found (``checked_states``), before the steps."""
        found = self.checked_states(positions)
        with self._states_lock:
            for position, read in found.items():
                if read is None:
                    continue
                slave, state = self.slaves[position], read[0]
                if state == SAFEOP | STATE_ERROR:
                    slave.state = SAFEOP | STATE_ACK
                    slave.write_state()
                elif state == SAFEOP:
                    slave.state = OP
                    slave.write_state()
        return found

    def watch_emergencies(self, on_emergency: Any) -> None:
        """Deliver the slaves' emergency messages (EMCY) to ``on_emergency(position, emcy)``;
        without a callback pysoem raises them from the next SDO to that slave, even a good one."""
        for position, slave in enumerate(self.slaves):
            slave.add_emergency_callback(lambda emcy, position=position: on_emergency(position, emcy))

    # ------------------------------------------------------------ SDO

    def sdo_read(self, position: int, index: int, subindex: int, size: int) -> bytes:
        slave = self.slaves[position]
        with self._sdo_errors(f"SDO read 0x{index:04X}:{subindex:02X} of {slave.name}"):
            return self._sdo_retried(slave, index, subindex, size)

    def sdo_write(self, position: int, index: int, subindex: int, data: bytes) -> None:
        slave = self.slaves[position]
        with self._sdo_errors(f"SDO write 0x{index:04X}:{subindex:02X} of {slave.name}"):
            slave.sdo_write(index, subindex, bytes(data), release_gil=True)

    @contextmanager
    def _sdo_errors(self, where: str) -> Iterator[None]:
        """pysoem's SDO errors as :class:`SdoAbortError`: the slave's abort code, or the frame lost."""
        try:
            yield
        except self.pysoem.SdoError as exc:
            raise SdoAbortError(where, exc.abort_code, exc.desc) from exc
        except self.lost_frame as exc:
            raise SdoAbortError(where, None, f"{type(exc).__name__}: {exc}") from exc

    # ------------------------------------------------------------ shutdown

    def close(self) -> None:
        """Every slave to INIT (best effort), then release the interface. Idempotent."""
        if not self.is_open:
            self._release_interface()
            return
        self.is_open = False
        try:
            if self.slaves:
                self.master.state = INIT
                self.master.write_state()
        except Exception as exc:  # the bus may be gone: closing must still release the socket
            log.warning("ethercat %s: writing INIT failed: %s", self.ifname, exc)
        self.master.close()
        self._release_interface()


ABORT_NO_OBJECT = 0x06020000  # SDO abort: the object does not exist in the object dictionary
RX_PDO_RANGE, TX_PDO_RANGE = (0x1600, 0x17FF), (0x1A00, 0x1BFF)  # CiA 301's PDO mapping objects


def sdo_count(where: str, index: int, data: bytes) -> int:
    """Subindex 0 of an assignment or a mapping object: its number of entries (u8, 0..254)."""
    if len(data) < 1:
        raise SlaveDataError(f"{where}: 0x{index:04X}:00 (number of entries) came back empty")
    if data[0] > 254:
        raise SlaveDataError(f"{where}: 0x{index:04X}:00 = {data[0]} entries, at most 254")
    return data[0]


def pdo_index(where: str, index: int, subindex: int, data: bytes) -> int:
    """Subindex n of 0x1C12 / 0x1C13: a PDO mapping object in the range of its direction."""
    if len(data) < 2:
        raise SlaveDataError(
            f"{where}: 0x{index:04X}:{subindex:02X} came back with {len(data)} byte(s), a PDO index needs 2"
        )
    pdo = struct.unpack_from("<H", data)[0]
    low, high = RX_PDO_RANGE if index == 0x1C12 else TX_PDO_RANGE
    if not low <= pdo <= high:
        raise SlaveDataError(
            f"{where}: 0x{index:04X}:{subindex:02X} = 0x{pdo:04X}, not a PDO of this "
            f"direction (0x{low:04X}..0x{high:04X})"
        )
    return pdo


def mapping_entry(where: str, index: int, subindex: int, data: bytes) -> int:
    """Subindex n of a PDO mapping object: index << 16 | subindex << 8 | bit length (1..64;
    index 0 pads)."""
    if len(data) < 4:
        raise SlaveDataError(
            f"{where}: 0x{index:04X}:{subindex:02X} came back with {len(data)} byte(s), a mapping entry needs 4"
        )
    entry = struct.unpack_from("<I", data)[0]
    if not 1 <= entry & 0xFF <= 64:
        raise SlaveDataError(
            f"{where}: 0x{index:04X}:{subindex:02X} = 0x{entry:08X}, a bit length of {entry & 0xFF} (1..64)"
        )
    return entry


def in_error(slaves: Sequence[Any]) -> bool:
    """Whether a slave's state (as last read) has the error bit."""
    return any(slave.state & STATE_ERROR for slave in slaves)


def reach_safeop(master: Any, timeout_s: float, poll_us: int = 50_000) -> bool:
    """Wait until every slave is in SAFEOP without an error (``read_state`` done either way),
    asking again each slave still in PREOP without one: SOEM asks once, at the end of
    ``config_map``, and a frame lost in a stall of the machine would leave its slave behind for
    good. A slave in another state is not asked, and one in error ends the wait at once (its AL
    status says why)."""
    deadline = time.monotonic() + timeout_s
    poll_us = max(poll_us, 1000)
    while True:
        # SOEM's check ORs every slave's state and masks the error bit: confirmed slave by slave
        if master.state_check(SAFEOP, poll_us) == SAFEOP:
            master.read_state()
            if all(slave.state == SAFEOP for slave in master.slaves):
                return True
        else:
            master.read_state()
        if time.monotonic() >= deadline or in_error(master.slaves):
            return False
        for slave in master.slaves:
            if slave.state == PREOP:
                slave.state = SAFEOP
                slave.write_state()


def reach_op(master: Any, exchange: Any, timeout_s: float, period_s: float, again_s: float = 0.1) -> bool:
    """SAFEOP → OP, with process data cycling (``exchange()``) before and during the request
    (``read_state`` done when it fails). The request (a broadcast) goes out again every
    ``again_s`` while the bus is not there, since a frame lost in a stall of the machine would
    leave it in SAFEOP until the timeout; before each repeat the states are read, and a slave
    in error ends the wait at once."""
    for _ in range(3):
        exchange()
        time.sleep(period_s)
    now = time.monotonic()
    deadline, again, first = now + timeout_s, now, True
    while time.monotonic() < deadline:
        if time.monotonic() >= again:
            if not first:
                master.read_state()
                if in_error(master.slaves):
                    return False
            master.state = OP  # (a state check overwrites it with what it read)
            master.write_state()
            again, first = time.monotonic() + again_s, False
        exchange()
        if master.state_check(OP, 1000) == OP:
            return True
        time.sleep(period_s)
    master.read_state()
    return False


def check_identity(
    position: int,
    device_name: str,
    name: str,
    vendor_id: int,
    product_code: int,
    want_vendor: int | None,
    want_product: int | None,
) -> None:
    """The slave at a position must be the configured device, when the config says which."""
    for what, want, got in (("vendor id", want_vendor, vendor_id), ("product code", want_product, product_code)):
        if want is not None and want != got:
            why = (
                f" (read as zero in {IDENTITY_READS} scans of the bus: its EEPROM did not answer in time)"
                if got == 0
                else ""
            )
            error = TransientBringUpError if got == 0 else BringUpError
            raise error(
                f"slave {position} ({device_name}): {what} 0x{got:08X}, "
                f"but the config expects 0x{want:08X} for {name!r}{why}"
            )


def _write_assignment(
    write: Callable[[int, int, bytes], None], assign: int, pdos: list[tuple[int, list[int]]], count: int | None = None
) -> None:
    """CiA 301's sequence: the assignment's count to 0, each PDO given entries mapped (its count
    0, the entries, the count), the PDOs assigned in order, the count. ``count``: how many of
    ``pdos`` are assigned (the rest only have their mapping written back)."""
    write(assign, 0, b"\0")
    for pdo, entries in pdos:
        if entries:
            write(pdo, 0, b"\0")
            for k, entry in enumerate(entries, 1):
                write(pdo, k, struct.pack("<I", entry))
            write(pdo, 0, bytes([len(entries)]))
    assigned = pdos if count is None else pdos[len(pdos) - count :]
    for k, (pdo, _) in enumerate(assigned, 1):
        write(assign, k, struct.pack("<H", pdo))
    write(assign, 0, bytes([len(assigned)]))


def _same_file(fd: int, path: Path) -> bool:
    """``fd`` is open on the file now at ``path``."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return False
    mine = os.fstat(fd)
    return (mine.st_dev, mine.st_ino) == (st.st_dev, st.st_ino)


def expected_wkc(infos: Sequence[SlaveInfo]) -> int:
    """Every slave in OP: 2 per slave with outputs, 1 per slave with inputs."""
    return sum(info.wkc for info in infos)
