"""A simulated CiA 402 drive on CANopen.

canopen's :class:`~canopen.LocalNode` is the node's communication side: object dictionary
from an EDS, SDO server, NMT slave, heartbeat producer, EMCY producer. It has no PDO engine,
so this class adds one: in OPERATIONAL, an RPDO of a synchronous transmission type (0..240)
is kept as it arrives and applied on the next SYNC, one of an event-driven type (254, 255) is
applied on receipt; on SYNC the servo model steps by the communication cycle period (0x1006),
and the TPDOs are sent. The PDOs are compiled from the node's own mapping and communication
objects each time it enters OPERATIONAL, so a master that remaps them in PRE-OPERATIONAL
gets what it asked for; a mapping entry the drive cannot map in that direction (or of
another size) is refused with SDO abort 0x06040041, as a drive does.

``rpdo_transmission_type`` sets the RPDOs' transmission type the node starts with (its
EDS's is 1), e.g. 255 as many drives ship.

The drive itself (state machine, CSP/CSV/CST servo model, faults and their EMCY codes) is the
simulated CiA 402 drive every bus simulator shares (:mod:`aiohal.simulation.cia402_drive`),
behind the application objects (0x6000 and up).

Fault injection: :meth:`inject_fault` (drive fault, EMCY with its code), :meth:`go_silent`
(the node stops: no heartbeat, no PDO, no SDO answer), :attr:`drop_tpdos` (the next n TPDO
cycles are not sent), :attr:`wrong_dlc` (TPDOs sent one byte short), :attr:`keep_mode` (a
mode written to 0x6060 by SDO is accepted and ignored: 0x6061 keeps showing the old one).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import cast

import canopen
from canopen.sdo import SdoAbortedError, SdoRecord

from aiohal.simulation.cia402_drive import DriveModel
from aiohal.simulation.od import ABORT_NOT_MAPPABLE, Entry, ObjectDictionary, PdoCodec, SdoAbort

log = logging.getLogger(__name__)

DATA = Path(__file__).resolve().parents[1] / "data"
DRIVE_EDS = DATA / "aiohal_drive.eds"
OPERATIONAL = 5
PRE_OPERATIONAL = 127
SYNC_COB_ID = 0x80
DEFAULT_CYCLE_US = 2000


class SimDrive:
    """One simulated drive node on a canopen :class:`~canopen.Network` (already connected)."""

    def __init__(
        self,
        network: canopen.Network,
        node_id: int,
        eds: str | Path = DRIVE_EDS,
        *,
        rpdo_transmission_type: int | None = None,
    ) -> None:
        self.network = network
        self.node_id = node_id
        self.node = canopen.LocalNode(node_id, str(eds))
        self.model_od = ObjectDictionary()  # the drive's application objects
        self._emergencies: list[tuple[int, int]] = []  # (code, register): sent after the SYNC's TPDOs
        self.model = DriveModel(self.model_od, lambda code, register: self._emergencies.append((code, register)))
        self.model.self_test_done()  # Switch on disabled
        self.lock = threading.Lock()  # the notifier thread and an injecting test
        self.rx: dict[int, PdoCodec] = {}
        self.rx_on_receipt: set[int] = set()  # COB-IDs of the event-driven RPDOs
        self.tx: list[tuple[int, PdoCodec]] = []
        self.pending: dict[int, bytes] = {}
        self.tx_buffer = bytearray(8)
        self.syncs = 0
        self.cycle_ns = DEFAULT_CYCLE_US * 1000
        self.silent = False
        self.drop_tpdos = 0
        self.wrong_dlc = False
        self.keep_mode = False
        self.operational = False
        self.node.add_read_callback(self._read_object)
        self.node.add_write_callback(self._write_object)
        if rpdo_transmission_type is not None:
            od = self.node.object_dictionary
            for k in range(512):
                if 0x1400 + k not in od:
                    break
                cast(SdoRecord, self.node.sdo[0x1400 + k])[2].raw = rpdo_transmission_type
        network.add_node(self.node)
        network.subscribe(0, self._after_nmt)  # after the node's own NMT slave (subscribed first)
        network.subscribe(SYNC_COB_ID, self._on_sync)
        self.node.nmt.state = "PRE-OPERATIONAL"
        network.send_message(0x700 + node_id, bytes([0]))  # boot-up

    # ------------------------------------------------------------ object dictionary bridge

    def _model_entry(self, index: int, subindex: int):
        if index < 0x6000:
            return None
        try:
            return self.model_od.entry(index, subindex)
        except SdoAbort:
            return None

    def _read_object(self, index: int, subindex: int, od) -> int | None:
        if index == 0x1018 and subindex == 4:
            return self.node_id  # serial number
        if index == 0x1001:
            return int(self.model.e_error_register.value)
        entry = self._model_entry(index, subindex)
        return None if entry is None else entry.value

    def _write_object(self, index: int, subindex: int, od, data: bytes) -> None:
        if index == 0x1006:
            self.cycle_ns = int.from_bytes(data, "little") * 1000 or DEFAULT_CYCLE_US * 1000
            return
        if subindex > 0 and (0x1600 <= index <= 0x17FF or 0x1A00 <= index <= 0x1BFF):
            self._check_mapping(index, int.from_bytes(data, "little"))
            return
        if self._model_entry(index, subindex) is None or (index == 0x6060 and self.keep_mode):
            return
        try:
            with self.lock:
                self.model_od.write(index, subindex, bytes(data))
        except SdoAbort as exc:
            raise SdoAbortedError(exc.code) from None

    def _check_mapping(self, index: int, word: int) -> None:
        """A mapping entry written: the object must exist and be mappable in the PDO's
        direction with its own size (0: the entry cleared)."""
        if word == 0:
            return
        target, sub, bits = word >> 16, (word >> 8) & 0xFF, word & 0xFF
        try:
            entry = self.model_od.entry(target, sub)
        except SdoAbort:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE) from None
        direction = "rx" if index < 0x1800 else "tx"
        if entry.mappable != direction or entry.bits != bits:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)

    # ------------------------------------------------------------ NMT and PDOs

    def _after_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        operational = self.node.nmt._state == OPERATIONAL
        if operational and not self.operational:
            self._compile_pdos()
        elif self.operational and not operational:
            with self.lock:
                self.model.outputs_lost(0)
        self.operational = operational

    def _compile_pdos(self) -> None:
        """The PDOs as the node's mapping objects say now (a master may have remapped them)."""
        sdo = self.node.sdo
        for cob_id in self.rx:
            self.network.unsubscribe(cob_id, self._on_rpdo)
        self.rx, self.tx = {}, []
        self.rx_on_receipt = set()
        od = self.node.object_dictionary
        for comm, mapping, rx in ((0x1400, 0x1600, True), (0x1800, 0x1A00, False)):
            for k in range(512):
                if comm + k not in od:
                    break
                # PDO communication and mapping parameters are records of UNSIGNED8/32 (CiA 301)
                comm_param = cast(SdoRecord, sdo[comm + k])
                mapping_param = cast(SdoRecord, sdo[mapping + k])
                cob_id = cast(int, comm_param[1].raw)
                if cob_id & 0x80000000:
                    continue
                items: list[tuple[Entry | None, int]] = []
                for sub in range(1, cast(int, mapping_param[0].raw) + 1):
                    value = cast(int, mapping_param[sub].raw)
                    index, subindex, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
                    items.append((self.model_od.entry(index, subindex), bits))
                codec = PdoCodec(items)
                if rx:
                    self.rx[cob_id & 0x7FF] = codec
                    if cast(int, comm_param[2].raw) >= 254:
                        self.rx_on_receipt.add(cob_id & 0x7FF)
                    self.network.subscribe(cob_id & 0x7FF, self._on_rpdo)
                else:
                    self.tx.append((cob_id & 0x7FF, codec))
        self.model.outputs_mapped([e for codec in self.rx.values() for e in codec.entries])

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        codec = self.rx.get(can_id)
        if codec is None or len(data) != codec.size or self.silent:
            return
        if can_id in self.rx_on_receipt:
            with self.lock:
                codec.decode(bytes(data), 0)
        else:
            self.pending[can_id] = bytes(data)

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not self.operational or self.silent:
            return
        with self.lock:
            for cob_id, payload in self.pending.items():
                self.rx[cob_id].decode(payload, 0)
            self.pending.clear()
            self.syncs += 1
            self.model.step(self.syncs * self.cycle_ns, True)
            emergencies, self._emergencies = self._emergencies, []
            frames = []
            if self.drop_tpdos > 0:
                self.drop_tpdos -= 1
            else:
                buf = self.tx_buffer
                for cob_id, codec in self.tx:
                    codec.encode(buf, 0)
                    size = codec.size - 1 if self.wrong_dlc else codec.size
                    frames.append((cob_id, bytes(buf[:size])))
        for code, register in emergencies:
            self.node.emcy.send(code, register)
        for cob_id, payload in frames:
            self.network.send_message(cob_id, payload)

    def configure(self, **settings) -> dict:
        """The drive model's settings (dynamics, servo, position, load, ...: see its configure)."""
        with self.lock:
            return self.model.configure(**settings)

    # ------------------------------------------------------------ fault injection

    def inject_fault(self, code: int = 0x2310) -> None:
        """A drive fault (default: over-current): fault reaction, EMCY with ``code``, then Fault."""
        with self.lock:
            self.model.inject_fault(code)

    def go_silent(self) -> None:
        """The node stops answering: no heartbeat, no TPDO, no SDO response."""
        self.silent = True
        self.node.nmt.stop_heartbeat()
        self.network.unsubscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)

    def status(self) -> dict:
        return {"node_id": self.node_id, "nmt": self.node.nmt.state, "syncs": self.syncs, **self.model.status()}

    def close(self) -> None:
        self.node.nmt.stop_heartbeat()
