"""``canopen``: CiA 402 drives on CANopen, over any python-can interface.

Bring-up runs off the tick (``asyncio.to_thread``): per node, NMT PRE-OPERATIONAL, identity
(0x1018) and device type (0x1000) checked against the config, the PDO mapping read from the
node with canopen (or written from the config), the mode of operation written and confirmed
by the drive's display of it (0x6061), communication cycle period and heartbeat producer
time written by SDO, NMT OPERATIONAL; then the drives are cycled until they are enabled
where they stand (bumpless, the CiA 402 logic of :mod:`aiohal.fieldbus.drives`). canopen's
own log lines are held back meanwhile: what fails is one exception that names the node.

Each tick, ``write`` sends every RPDO and then SYNC: a drive applies a synchronous RPDO on
that SYNC, an event-driven one (254, 255) on receipt; the drives answer with their TPDOs,
which are copied into one input buffer (a slice per TPDO, a frame of the wrong length is
counted and dropped) as they arrive, and the next ``read`` decodes. Nothing in the tick
waits: frames are sent without blocking and a TPDO that has not arrived leaves the joints
unrefreshed (the loop's stale-feedback check then holds the robot).

Who takes the received frames: canopen's notifier thread during bring-up and close; once the
drives are up, on a bus with a file descriptor (socketcan, udp_multicast, ...), the event
loop's thread between ticks (:meth:`CanopenDriver._receive_on_the_loop`), so that no other
thread of the process runs Python beside the tick: such a thread takes the GIL whenever the
tick releases it, and one the host preempts while holding it stalls the tick for a whole
time slice. python-can's ``virtual`` bus has no descriptor and keeps the thread.

Heartbeat consumer: a node silent for ``heartbeat_timeout_ms`` fails the driver (the loop
sends the robot to its safe state). EMCY frames are decoded by canopen; each is reported
as the drive's emergency with its code and the code's meaning, and a drive fault holds the robot until :meth:`CanopenDriver.reset_faults`.
SDO access (:meth:`sdo_read`, :meth:`sdo_write`) runs in a worker thread, never on the tick.
"""

from __future__ import annotations

import asyncio
import io
import logging
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast

import can  # the `can` extra; a missing one is reported by the plugin loader
import canopen
import numpy as np
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.pdo import PdoBase, PdoMaps
from pydantic import Field

from aiohal.config import ConfigPath
from aiohal.errors import AiohalError
from aiohal.fieldbus.busvar import decode_mapping
from aiohal.fieldbus.cia402 import DriveEvent, DriveUnits, EventKind
from aiohal.fieldbus.cia402_driver import Cia402Driver
from aiohal.fieldbus.drives import DriveGroup, DriveSpec
from aiohal.fieldbus.error_codes import describe_error_code, describe_error_register
from aiohal.fieldbus.pdo_options import DriveUnitOptions, parse_number, parse_pdo_entry, pdo_issues
from aiohal.files import FileRefused, read_regular_text
from aiohal.hal import FiniteFloat, JointValues, Options, unknown_joint_issues
from aiohal.logutil import RateLimitedLogger
from aiohal.robot import Fault
from aiohal.safety.watchdog import SendCanFrame, can_frame
from aiohal.simulation.servo import ServoParams

from . import busload
from .sensors import SENSORS_DBC, DbcSensor, SensorGateway, SensorOptions, load_dbc, sensor_issues

if TYPE_CHECKING:
    from .sim import SimBus

log = logging.getLogger(__name__)

DATA = Path(__file__).resolve().parent / "data"
DRIVE_EDS = DATA / "aiohal_drive.eds"
MODES = {"csp": 8, "csv": 9, "cst": 10}
MODE_NAMES = {
    0: "no mode",
    1: "profile position",
    3: "profile velocity",
    4: "profile torque",
    6: "homing",
    7: "interpolated position",
    **{value: name for name, value in MODES.items()},
}
# (index, subindex, bits) of each drive variable, in DRIVE_INPUTS / DRIVE_OUTPUTS (+ DRIVE_OFFSETS) order
INPUT_OBJECTS = ((0x6041, 0, 16), (0x6064, 0, 32), (0x606C, 0, 32), (0x6077, 0, 16), (0x603F, 0, 16))
OUTPUT_OBJECTS = (
    (0x6040, 0, 16),
    (0x607A, 0, 32),
    (0x60FF, 0, 32),
    (0x6071, 0, 16),
    (0x6060, 0, 8),
    (0x60B1, 0, 32),
    (0x60B2, 0, 16),
)  # then DRIVE_OFFSETS, where a drive maps them
REQUIRED = {0x6041, 0x6064, 0x6040, 0x607A}
SPARE = 8  # zero bytes past each buffer's data, where unmapped variables point
SYNC_COB_ID = 0x80
NMT_COB_ID, NMT_STOP = 0x000, 0x02
CAN_ERR_BUSOFF = 0x40  # error class of a socketcan error frame (linux/can/error.h)
#: frames taken per wake-up of the loop's reader: a whole cycle's TPDOs and sensor frames
#: several times over, and a bound a flooded bus cannot push the tick past
FRAMES_PER_WAKE = 64
#: receptions failing in a row before the driver gives the bus up (a fault: the safe state)
RX_FAILURES_LIMIT = 100


class CanopenError(AiohalError, RuntimeError):
    """A CANopen bus or node that cannot be used (bring-up) or was lost (heartbeat)."""


class NodeOptions(Options):
    node_id: int = Field(ge=1, le=127, description="CANopen node id.")
    name: str | None = Field(None, description="Shown in reports; default node<id>.")
    joint: str = Field(description="The joint this CiA 402 drive moves.")
    eds: ConfigPath | None = Field(None, description="EDS/DCF of the node; default: aiohal's simulated drive.")
    vendor_id: int | None = Field(None, ge=0, description="0x1018:1, checked at bring-up when given.")
    product_code: int | None = Field(None, ge=0, description="0x1018:2, checked at bring-up when given.")
    mode: Literal["csp", "csv", "cst"] = Field(
        "csp", description="Mode of operation written at bring-up (0x6060) and confirmed by the drive (0x6061)."
    )
    counts_per_rev: FiniteFloat | None = Field(None, gt=0)
    gear_ratio: FiniteFloat | None = Field(None, gt=0)
    rated_torque: FiniteFloat | None = Field(None, gt=0)
    position_offset: FiniteFloat = Field(0.0, description="rad added to the drive's position.")
    rx_pdos: dict[str, list[str]] | None = Field(
        None,
        description="Remap the RPDOs: per mapping object (0x1600..), its entries 'index:subindex:bits' "
        "(e.g. '0x607A:0:32'); written by SDO in PRE-OPERATIONAL and read back. RPDOs not "
        "listed are disabled. Leave out to use the node's own mapping.",
    )
    tx_pdos: dict[str, list[str]] | None = Field(None, description="Remap the TPDOs (0x1A00..), as rx_pdos.")

    @property
    def label(self) -> str:
        return self.name or f"node{self.node_id}"

    def remaps(self) -> list[tuple[str, dict[int, list[tuple[int, int, int]]]]]:
        """("rpdo" or "tpdo", {PDO number (1-based): [(index, subindex, bits)]}) for each direction
        the config remaps; checked by check_config."""
        out = []
        for kind, pdos, base in (("rpdo", self.rx_pdos, 0x1600), ("tpdo", self.tx_pdos, 0x1A00)):
            if pdos is not None:
                out.append(
                    (
                        kind,
                        {
                            parse_number(m) - base + 1: [decode_mapping(parse_pdo_entry(e)) for e in entries]
                            for m, entries in pdos.items()
                        },
                    )
                )
        return out


class SimulationOptions(Options):
    """The simulated drives of ``simulate = true``."""

    dynamics: Literal["motor", "servo"] = Field(
        "motor",
        description="motor: a simple motor model; servo: aiohal.simulation.servo's cascade (LOLA's, a hip-like joint "
        "behind servo.gear_ratio, which every node's gear_ratio must match).",
    )
    servo: ServoParams = Field(default_factory=ServoParams, description="The drives and joints of dynamics = servo.")


class CanopenOptions(Options):
    interface: str = Field(min_length=1, description="python-can interface: socketcan, pcan, kvaser, virtual, ...")
    channel: str = Field(min_length=1, description="python-can channel, e.g. can0.")
    bitrate: int = Field(1_000_000, ge=10_000, le=1_000_000, description="Nominal bitrate (bit/s).")
    data_bitrate: int | None = Field(
        None, ge=10_000, le=8_000_000, description="CAN FD data bitrate, where the interface has it (enables FD)."
    )
    nodes: list[NodeOptions] = Field(default_factory=list, description="Every CiA 402 drive on this bus.")
    dbc: ConfigPath | None = Field(
        None, description="DBC file of the sensors' frames; default: aiohal's simulated gateway's."
    )
    sensors: list[SensorOptions] = Field(
        default_factory=list, description="IMU and force/torque sensors whose frames the DBC describes."
    )
    drive_defaults: DriveUnitOptions = Field(default_factory=DriveUnitOptions)
    heartbeat_ms: int = Field(50, ge=1, le=65535, description="Heartbeat producer time written to every node (0x1017).")
    heartbeat_timeout_ms: FiniteFloat = Field(200.0, gt=0, description="A node silent this long is lost.")
    sdo_timeout_s: FiniteFloat = Field(0.5, gt=0, description="SDO response timeout at bring-up.")
    mode_timeout_s: FiniteFloat = Field(
        0.5,
        gt=0,
        le=10,
        description="How long bring-up waits for a drive to show the mode written to 0x6060 in 0x6061.",
    )
    enable_timeout_s: FiniteFloat = Field(3.0, gt=0)
    stuck_after_ms: FiniteFloat = Field(1000.0, gt=0, description="A drive making no progress this long is faulted.")
    tx_error_limit: int = Field(
        10,
        ge=1,
        le=10_000,
        description="Cycles in a row whose frames could not all be sent (bus-off, no ACK) before the driver fails.",
    )
    simulate: bool = Field(
        False,
        description="Start aiohal's simulated drives on this bus in this process "
        "(interface virtual: a demo with one command).",
    )
    initial_position: JointValues = Field(
        0.0, description="simulate: where the simulated joints start (rad), scalar or per joint."
    )
    simulation: SimulationOptions = Field(default_factory=SimulationOptions)
    estop_frame: str | None = Field(
        None,
        pattern=r"^([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#([0-9A-Fa-f]{2}){0,8}$",
        description="The frame the watchdog process sends when the tick stops, candump style: 'ID#DATA' (3 hex "
        "digits: 11-bit id, 8: 29-bit), e.g. a safety relay's e-stop message. Default: NMT Stop to "
        "every node (000#0200). socketcan only: other interfaces are not reachable from another process.",
    )


def estop_can_frame(spec: str | None) -> bytes:
    """The ``struct can_frame`` of ``estop_frame`` ('ID#DATA'); None: NMT Stop (command 0x02)
    to every node (node id 0), which leaves their PDOs and, per their abort connection option
    (0x6007), stops the drives."""
    if spec is None:
        return can_frame(NMT_COB_ID, bytes((NMT_STOP, 0)))
    ident, data = spec.split("#")
    return can_frame(int(ident, 16), bytes.fromhex(data), extended=len(ident) == 8)


class _ErrorFrames(can.Listener):
    """Counts error frames and notes bus-off (where the frames are received)."""

    def __init__(self, driver: CanopenDriver) -> None:
        self.driver = driver

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.driver.error_frames += 1
            if msg.arbitration_id & CAN_ERR_BUSOFF:
                self.driver.bus_off = True


@contextmanager
def canopen_quiet() -> Iterator[None]:
    """canopen's own log lines hidden while the block runs (bring-up): an SDO it aborts, a
    retry, a node that does not answer. What goes wrong there is one exception of aiohal's that
    names the node, the object and the cause. Outside such blocks canopen's warnings and errors
    are shown, not its info lines (every NMT, SDO and PDO step). A level the user gave the
    ``canopen`` logger (other than WARNING) is left alone."""
    logger = logging.getLogger("canopen")
    if logger.level not in (logging.NOTSET, logging.WARNING):
        yield
        return
    logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        logger.setLevel(logging.WARNING)


def transmission_type_issue(kind: str, trans_type: int | None) -> str | None:
    """Why a PDO of this transmission type cannot be used (None: it can). ``write`` sends
    every RPDO just before SYNC: a synchronous RPDO (0..240) is applied on that SYNC, an
    event-driven one (254, 255) on receipt, the same cycle (docs/canopen.md). A TPDO must be
    synchronous: its drive sends it on SYNC."""
    if trans_type is None:
        return None
    if kind == "RPDO" and not (trans_type <= 240 or trans_type >= 254):
        return f"transmission type {trans_type}, which an RPDO cannot have (0..240 synchronous, 254/255 event-driven)"
    if kind == "TPDO" and trans_type > 240:
        return f"transmission type {trans_type}; this driver needs synchronous TPDOs (1..240)"
    return None


def _entries_text(entries) -> str:
    return ", ".join(f"0x{index:04X}:{subindex}:{bits}" for index, subindex, bits in entries) or "none"


def load_od(path: str | Path, node_id: int, key: str = "options.nodes[].eds") -> canopen.ObjectDictionary:
    """A node's EDS/DCF, read here and handed to canopen as text: a regular file only."""
    text = io.StringIO(read_regular_text(path, key))
    text.name = str(path)  # canopen picks the format by the name's suffix
    return canopen.import_od(text, node_id)


def configured_frames(options: CanopenOptions) -> tuple[list[int], list[tuple[int, float]]]:
    """The frames the config implies, as its EDS/DCF files and DBC say: per cycle (every
    enabled RPDO, SYNC, every enabled TPDO: data bytes), and the sensors' ((bytes, Hz))."""
    cyclic = [0]  # SYNC
    for node in options.nodes:
        od = load_od(node.eds or DRIVE_EDS, node.node_id)
        remapped = dict(node.remaps())
        for kind, comm, mapping in (("rpdo", 0x1400, 0x1600), ("tpdo", 0x1800, 0x1A00)):
            if kind in remapped:
                cyclic += [(sum(bits for *_, bits in entries) + 7) // 8 for entries in remapped[kind].values()]
                continue
            for k in range(512):
                if comm + k not in od or mapping + k not in od:
                    break
                # PDO communication and mapping parameters have sub-indices (CiA 301: records)
                comm_param = cast("ODRecord | ODArray", od[comm + k])
                mapping_param = cast("ODRecord | ODArray", od[mapping + k])
                cob_id = _od_value(comm_param[1])
                count = _od_value(mapping_param[0])
                if cob_id & 0x80000000 or not count:
                    continue
                bits = sum(_od_value(mapping_param[sub]) & 0xFF for sub in range(1, count + 1))
                cyclic.append((bits + 7) // 8)
    sensors = []
    if options.sensors:
        db = load_dbc(str(options.dbc or SENSORS_DBC))
        rates: dict[int, float] = {}
        for sensor in options.sensors:
            names = [n for names in sensor.signals.values() for n in names] + ([sensor.status] if sensor.status else [])
            for name in names:
                frame = db.get_message_by_name(name.partition(".")[0])
                rates[frame.frame_id] = max(rates.get(frame.frame_id, 0.0), 1000.0 / sensor.period_ms)
        sensors = [(db.get_message_by_frame_id(f).length, hz) for f, hz in rates.items()]
    return cyclic, sensors


def _pdo_maps(pdos: PdoBase) -> PdoMaps:
    """A node's RPDO or TPDO maps by number: canopen's RPDO and TPDO build them once, in __init__."""
    return cast(PdoMaps, pdos.map)


def _od_value(var: ODVariable) -> int:
    """An object's value as the EDS/DCF sets it (a DCF's ParameterValue before the default)."""
    # the PDO parameters this reads have a DefaultValue in any EDS (int(None) would raise)
    return int(cast(int, var.value if var.value is not None else var.default))


class CanopenDriver(Cia402Driver):
    Options = CanopenOptions
    bus_name = "canopen"
    device_kinds = frozenset({"imu", "force_torque"})
    options: CanopenOptions

    @classmethod
    def check_config(cls, options, joints, devices, robot):
        issues = unknown_joint_issues("options.initial_position", options.initial_position, joints)
        ids: dict[int, int] = {}
        moved: dict[str, int] = {}
        for i, node in enumerate(options.nodes):
            where = f"options.nodes[{i}]"
            if node.node_id in ids:
                issues.append((f"{where}.node_id", f"{node.node_id} is also the id of nodes[{ids[node.node_id]}]"))
            ids.setdefault(node.node_id, i)
            if node.joint not in joints:
                issues.append((f"{where}.joint", f'"{node.joint}" is not one of this driver\'s joints {joints}'))
            elif node.joint in moved:
                issues.append((f"{where}.joint", f'"{node.joint}" is already moved by nodes[{moved[node.joint]}]'))
            moved.setdefault(node.joint, i)
            if node.eds is not None:
                try:
                    load_od(node.eds, node.node_id, key="")
                except FileRefused as exc:
                    issues.append((f"{where}.eds", str(exc)))
                except Exception as exc:  # canopen's parser raises what its parsing met
                    issues.append((f"{where}.eds", f"{node.eds}: not a readable EDS/DCF ({type(exc).__name__}: {exc})"))
            issues += pdo_issues(f"{where}.rx_pdos", node.rx_pdos, 0x1600, 0x17FF)
            issues += pdo_issues(f"{where}.tx_pdos", node.tx_pdos, 0x1A00, 0x1BFF)
        for joint in joints:
            if joint not in moved:
                issues.append(("joints", f'joint "{joint}" has no node in options.nodes'))
        if options.simulate and any(n.eds is not None and Path(n.eds) != DRIVE_EDS for n in options.nodes):
            issues.append(("options.simulate", "the simulated drives have aiohal's own EDS: leave nodes[].eds out"))
        if options.simulate and options.simulation.dynamics == "servo":
            gear = options.simulation.servo.gear_ratio
            for i, node in enumerate(options.nodes):
                ratio = node.gear_ratio or options.drive_defaults.gear_ratio
                if ratio != gear:
                    issues.append(
                        (
                            f"nodes[{i}].gear_ratio",
                            f"{ratio:g}, but the simulated servo's joint is behind options.simulation.servo."
                            f"gear_ratio = {gear:g}: the units would not match the drive",
                        )
                    )
        issues += cls._sensor_issues(options, devices)
        return issues

    @staticmethod
    def _sensor_issues(options: CanopenOptions, devices: dict[str, str]) -> list[tuple[str, str]]:
        if not options.sensors:
            return [("devices", f'device "{name}" has no entry in options.sensors') for name in devices]
        dbc = options.dbc or SENSORS_DBC
        try:
            db = load_dbc(str(dbc))
        except Exception as exc:  # an unreadable file: OSError, or cantools's own parse errors
            return [("options.dbc", f"cannot load {dbc}: {exc}")]
        issues = []
        served = set()
        for i, sensor in enumerate(options.sensors):
            issues += sensor_issues(f"options.sensors[{i}]", sensor, devices.get(sensor.device), db)
            served.add(sensor.device)
        issues += [
            ("devices", f'device "{name}" has no entry in options.sensors') for name in devices if name not in served
        ]
        return issues

    @classmethod
    def check_rate(cls, options, cycle_hz, every):
        """Refuse a bus that the configured frames would load above 100 % at the driver's rate."""
        try:
            cyclic, sensors = configured_frames(options)
        except Exception as exc:  # an unreadable EDS or DBC is reported by check_config
            log.debug("bus load not computed: %s", exc)
            return []
        load = busload.load(cyclic, cycle_hz, options.bitrate) + busload.load_at(sensors, options.bitrate)
        if load <= 1.0:
            return []
        sensor_load = busload.load_at(sensors, options.bitrate)
        per_cycle = sum(busload.frame_bits(n) for n in cyclic)
        fits = per_cycle / max(1e-9, (1.0 - sensor_load) * options.bitrate)  # seconds per cycle needed
        needed = max(every + 1, int(np.ceil(fits * cycle_hz * every)))
        return [
            (
                "every",
                f"the CAN bus would be {100 * load:.0f} % loaded: {len(cyclic)} frames of {per_cycle} bits "
                f"per cycle (worst-case bit stuffing) at {cycle_hz:g} Hz, and the sensors' frames, on "
                f"{options.bitrate} bit/s; run this driver on fewer ticks (every = {needed}), raise the "
                "bitrate, map fewer PDOs or slow the sensors",
            )
        ]

    def __init__(self, name, view, options) -> None:
        super().__init__(name, view, options)
        self._init_drive_state()  # the drives, the lock on the bus's cycles and their state, no estop
        self._reader: tuple[asyncio.AbstractEventLoop, int] | None = None  # the loop watching the bus
        self._rx_failures = 0  # receptions in a row that raised (the loop's reader)
        self._rx_error: BaseException | None = None  # why the loop's reader gave up
        self.rx_errors = 0
        self.sim: SimBus | None = None  # simulate: the simulated nodes
        self.bus: can.BusABC | None = None
        self.network: canopen.Network | None = None
        self.remotes: list[canopen.RemoteNode] = []
        self.gateway: SensorGateway | None = None
        self._inputs = np.zeros(SPARE, dtype=np.uint8)
        self._outputs = np.zeros(SPARE, dtype=np.uint8)
        self._out_view = memoryview(self._outputs.data).cast("B")  # the RPDOs' bytes, sliced per frame
        self._rpdos: list[tuple[can.Message, int, int]] = []
        self._sync = can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False)
        self._tpdos_per_cycle = 0
        self._frame_sizes: list[int] = []
        self._heard = np.zeros(len(options.nodes))  # monotonic time of each node's last heartbeat
        self._next_heartbeat_check = 0.0
        self._last_read_s = 0.0  # monotonic time of the last read() (a gap in them is a stall)
        self._heartbeat_check_s = options.heartbeat_timeout_ms * 1e-4
        self._emcy: deque[tuple[int, int, int]] = deque()  # (node index, code, register) as received
        self._last_emcy = [0] * len(options.nodes)  # each node's last EMCY error code (0: none or reset)
        self._warn = RateLimitedLogger(log)
        self._active = False
        self._written = False  # write() sent this tick's cycle (the loop skips write below hold)
        self._seen = 0
        self._failed_cycles = 0  # cycles in a row with a frame not sent
        self.bus_off = False  # an error frame said bus-off (socketcan error class 0x40)
        self.error_frames = 0
        self.cycles = 0
        self.tx_frames = 0
        self.tx_errors = 0
        self.rx_tpdos = 0
        self.malformed = 0
        self.late_cycles = 0
        self.emergencies = 0
        self.lost_nodes: list[str] = []
        self._started_ns = 0

    # ------------------------------------------------------------ lifecycle

    async def open(self) -> None:
        await asyncio.to_thread(self._quiet_bring_up)
        self._receive_on_the_loop()

    def _receive_on_the_loop(self) -> None:
        """Hand reception from canopen's notifier thread to this event loop (the tick's
        thread), where the bus has a file descriptor: its frames are then taken between ticks."""
        network, bus = self.network, self.bus
        if network is None or bus is None or network.notifier is None:
            return
        try:
            fd = bus.fileno()
        except NotImplementedError:  # python-can's virtual bus: the thread stays
            return
        if fd < 0:
            return
        network.notifier.stop(2 * network.NOTIFIER_CYCLE + 1.0)  # its thread ends within a receive timeout
        network.notifier = None
        loop = asyncio.get_running_loop()
        loop.add_reader(fd, self._on_readable)
        self._reader = (loop, fd)

    def _on_readable(self) -> None:
        """The frames waiting on the bus, on the loop's thread: at most ``FRAMES_PER_WAKE``,
        so that a flood still leaves the tick its turn (the rest come on the next wake-up)."""
        bus, listeners = self.bus, self.network.listeners  # type: ignore[union-attr]  # set while watched
        try:
            for _ in range(FRAMES_PER_WAKE):
                msg = bus.recv(0.0)  # type: ignore[union-attr]
                if msg is None:
                    break
                for listener in listeners:
                    listener.on_message_received(msg)
            self._rx_failures = 0
        except Exception as exc:  # a receive that fails (interface down) or a callback's error
            self.rx_errors += 1
            self._rx_failures += 1
            self._warn.warning("rx", "canopen %s: receiving failed: %s", self.name, exc)
            if self._rx_failures >= RX_FAILURES_LIMIT:  # a bus that fails every time: no busy loop
                self._rx_error = exc
                self._stop_reader()

    def _stop_reader(self) -> None:
        if self._reader is not None:
            loop, fd = self._reader
            self._reader = None
            loop.remove_reader(fd)

    def _quiet_bring_up(self) -> None:
        with canopen_quiet():
            self._bring_up()

    def _cycle_ns(self) -> int:
        """The bus's cycle: the loop's period times the driver's ``every``."""
        return self.view.clock.period_ns * self.view.every

    def _bus_options(self) -> dict[str, Any]:
        opts = self.options
        kwargs: dict[str, Any] = {"interface": opts.interface, "channel": opts.channel, "bitrate": opts.bitrate}
        if opts.data_bitrate is not None:
            kwargs.update(fd=True, data_bitrate=opts.data_bitrate)
        if opts.interface == "virtual":
            kwargs["receive_own_messages"] = False
        return kwargs

    def _bring_up(self) -> None:
        opts = self.options
        if opts.simulate:
            from .sim import SimBus

            self.sim = SimBus(
                opts.interface,
                opts.channel,
                [n.node_id for n in opts.nodes],
                bitrate=opts.bitrate,
                sensors={self.view.device_kinds[s.device]: s.period_ms * 1e-3 for s in opts.sensors}
                if opts.sensors
                else None,
            )
            initial = self.view.per_joint(opts.initial_position)
            dynamics: dict[str, Any] = {"dynamics": opts.simulation.dynamics}
            if opts.simulation.dynamics == "servo":
                dynamics["servo"] = opts.simulation.servo.model_dump()
            for node_opts, units in zip(opts.nodes, self._units(), strict=True):
                q = initial[self.view.joint_names.index(node_opts.joint)]
                self.sim.drives[node_opts.node_id].configure(
                    **dynamics, position=(q - node_opts.position_offset) * units.counts_per_rad
                )
        try:
            self.bus = can.Bus(**self._bus_options())
        except (can.CanError, OSError, ValueError) as exc:
            raise CanopenError(f"cannot open the CAN bus {opts.interface}:{opts.channel}: {exc}") from exc
        self.network = network = canopen.Network(self.bus)
        network.NOTIFIER_CYCLE = 0.05  # its thread's receive timeout: how long closing waits for it
        # canopen drops error frames; bus-off is in them. Its notifier takes any can.Listener
        # (canopen's list is typed by its first item, its own MessageListener).
        cast(list[can.Listener], network.listeners).append(_ErrorFrames(self))
        network.connect()
        tpdo_slices: list[tuple[int, int, int]] = []  # (cob id, start, size) in the input buffer
        rpdo_slices: list[tuple[int, int, int]] = []
        offsets = []
        for k, node_opts in enumerate(opts.nodes):
            node = canopen.RemoteNode(node_opts.node_id, load_od(node_opts.eds or DRIVE_EDS, node_opts.node_id))
            node.sdo.RESPONSE_TIMEOUT = opts.sdo_timeout_s
            network.add_node(node)
            self.remotes.append(node)
            node.nmt.send_command(0x80)  # PRE-OPERATIONAL: PDO mapping and parameters may change
            self._check_identity(k, node)
            node.tpdo.read()
            node.rpdo.read()
            for kind, pdos in node_opts.remaps():
                self._remap(k, node, kind, pdos)
            inputs = self._place(k, _pdo_maps(node.tpdo), INPUT_OBJECTS, tpdo_slices, "TPDO")
            outputs = self._place(k, _pdo_maps(node.rpdo), OUTPUT_OBJECTS, rpdo_slices, "RPDO")
            offsets.append((inputs, outputs))
            self._set_mode(k, node)
            node.sdo[0x1006].raw = self._cycle_ns() // 1000
            node.sdo[0x1017].raw = opts.heartbeat_ms
            node.nmt.add_heartbeat_callback(self._heartbeat_callback(k))
            node.emcy.add_callback(self._emcy_callback(k))
        in_size = sum(size for _, _, size in tpdo_slices)
        out_size = sum(size for _, _, size in rpdo_slices)
        self._inputs = np.zeros(in_size + SPARE, dtype=np.uint8)
        self._outputs = np.zeros(out_size + SPARE, dtype=np.uint8)
        self._out_view = memoryview(self._outputs.data).cast("B")
        resolved = [
            [in_size if o is None else o for o in inputs] + [out_size if o is None else o for o in outputs]
            for inputs, outputs in offsets
        ]
        if opts.nodes:
            self._link(resolved)
        self._rpdos = [
            (can.Message(arbitration_id=cob, data=bytearray(size), is_extended_id=False), start, start + size)
            for cob, start, size in rpdo_slices
        ]
        self._tpdos_per_cycle = len(tpdo_slices)
        self._frame_sizes = [size for _, _, size in rpdo_slices] + [0] + [size for _, _, size in tpdo_slices]
        inputs_view = memoryview(self._inputs.data).cast("B")
        for cob, start, size in tpdo_slices:
            network.subscribe(cob, self._tpdo_callback(inputs_view[start : start + size], size))
        if opts.sensors:
            db = load_dbc(str(opts.dbc or SENSORS_DBC))
            sensors = [
                DbcSensor(s, self.view.devices[s.device], self.view.device_kinds[s.device], db) for s in opts.sensors
            ]
            self.gateway = SensorGateway(sensors, db, self.name)
            self.gateway.subscribe(network)
        self._heard[:] = time.monotonic()
        for node in self.remotes:
            node.nmt.send_command(0x01)  # OPERATIONAL
        if self.drives is not None:
            self._wait_enabled(opts.enable_timeout_s)
        self._started_ns = time.monotonic_ns()
        self._written = True  # the first tick's read() sends nothing: its write() does
        self._active = True

    def _check_identity(self, k: int, node: canopen.RemoteNode) -> None:
        want = self.options.nodes[k]
        try:
            device_type = node.sdo[0x1000].raw
        except canopen.SdoCommunicationError:
            opts = self.options
            raise CanopenError(
                f"node {want.node_id} ({want.label}, joint {want.joint}) does not answer on "
                f"{opts.interface}:{opts.channel}: no response to an SDO read of its device type (0x1000) "
                f"within {opts.sdo_timeout_s:g} s; check that it is powered, on this bus, at "
                f"{opts.bitrate} bit/s and has node id {want.node_id}"
            ) from None
        except canopen.SdoAbortedError as exc:
            raise CanopenError(
                f"node {want.node_id} ({want.label}): its device type (0x1000) cannot be read: SDO abort {exc}"
            ) from None
        try:
            vendor, product = node.sdo[0x1018][1].raw, node.sdo[0x1018][2].raw
        except (canopen.SdoCommunicationError, canopen.SdoAbortedError) as exc:
            raise CanopenError(
                f"node {want.node_id} ({want.label}): its identity (0x1018) cannot be read: {exc}"
            ) from None
        if device_type & 0xFFFF != 402:
            raise CanopenError(
                f"node {want.node_id} ({want.label}): device type 0x{device_type:08X} is not a "
                "CiA 402 drive (profile 402 in 0x1000)"
            )
        for what, got, expected in (
            ("vendor id", vendor, want.vendor_id),
            ("product code", product, want.product_code),
        ):
            if expected is not None and got != expected:
                raise CanopenError(
                    f"node {want.node_id} ({want.label}): {what} 0x{got:08X}, the config says 0x{expected:08X}"
                )

    def _remap(self, k: int, node: canopen.RemoteNode, kind: str, pdos: dict[int, list[tuple[int, int, int]]]) -> None:
        """Write the configured mapping (the others disabled), then read it back: a node that
        accepts the writes but keeps its own mapping is refused, not believed."""
        want = self.options.nodes[k]
        maps = node.rpdo if kind == "rpdo" else node.tpdo
        by_number = _pdo_maps(maps)
        for number, pdo in by_number.items():
            entries = pdos.get(number)
            if entries is None:
                if pdo.enabled:
                    pdo.enabled = False
                    self._save_pdo(k, kind, number, pdo, [])
                continue
            pdo.clear()
            try:
                for index, subindex, bits in entries:
                    pdo.add_variable(index, subindex, bits)
            except KeyError as exc:
                raise CanopenError(
                    f"node {want.node_id} ({want.label}): {kind.upper()}{number}: {exc.args[0]} is not "
                    "in the node's EDS"
                ) from None
            pdo.enabled = True
            if transmission_type_issue(kind.upper(), pdo.trans_type) is not None:
                pdo.trans_type = 1  # else the node's own: an event-driven RPDO stays so
            self._save_pdo(k, kind, number, pdo, entries)
        missing = sorted(set(pdos) - set(by_number))
        if missing:
            raise CanopenError(f"node {want.node_id} ({want.label}): no {kind.upper()} {missing} in its EDS")
        maps.read()
        for number, entries in pdos.items():
            got = [(v.index, v.subindex, v.length) for v in by_number[number].map]
            if got != entries or not by_number[number].enabled:
                raise CanopenError(
                    f"node {want.node_id} ({want.label}): {kind.upper()}{number} reads back as {got} "
                    f"after writing {entries}: the node kept its own mapping"
                )

    def _save_pdo(self, k: int, kind: str, number: int, pdo, entries: list[tuple[int, int, int]]) -> None:
        """Write one PDO's parameters and mapping; a node that refuses them is named with the
        PDO, its COB-ID, the entries and the SDO abort code and its meaning."""
        want = self.options.nodes[k]
        try:
            pdo.save()
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
            what = "SDO abort" if isinstance(exc, canopen.SdoAbortedError) else "no SDO answer"
            action = f"mapping {_entries_text(entries)}" if pdo.enabled else "disabling it"
            raise CanopenError(
                f"node {want.node_id} ({want.label}) refused {kind.upper()}{number} (COB-ID 0x{pdo.cob_id:03X}, "
                f"{action}): {what}: {exc}"
            ) from None

    def _set_mode(self, k: int, node: canopen.RemoteNode) -> None:
        """Write the mode of operation (0x6060), then wait for the drive to show it (0x6061)
        within ``mode_timeout_s``: a drive that runs another mode is refused."""
        want, opts = self.options.nodes[k], self.options
        asked = MODES[want.mode]
        who = f"node {want.node_id} ({want.label})"
        try:
            node.sdo.download(0x6060, 0, asked.to_bytes(1, "little", signed=True))
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
            raise CanopenError(f"{who} refused mode {want.mode} ({asked}) in 0x6060: {exc}") from None
        deadline = time.monotonic() + opts.mode_timeout_s
        for _ in range(1000):  # bounded: the deadline ends it first
            try:
                shown = int.from_bytes(node.sdo.upload(0x6061, 0)[:1], "little", signed=True)
            except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
                raise CanopenError(
                    f"{who}: the mode it runs cannot be read (0x6061, modes of operation display): {exc}"
                ) from None
            if shown == asked or time.monotonic() >= deadline:
                break
            time.sleep(0.01)
        if shown != asked:
            raise CanopenError(
                f"{who}: mode {want.mode} ({asked}) written to 0x6060, but the drive shows "
                f"{MODE_NAMES.get(shown, 'an unknown mode')} ({shown}) in 0x6061 after {opts.mode_timeout_s:g} s: "
                "it does not run the mode asked"
            )

    def _place(self, k: int, maps: PdoMaps, objects, slices: list, kind: str) -> list[int | None]:
        """Lay this node's enabled PDOs end to end in its direction's buffer; the offset of
        each drive variable in them (None: not mapped)."""
        want = self.options.nodes[k]
        network = cast(canopen.Network, self.network)  # bring-up has connected it
        found: dict[tuple[int, int], tuple[int, int]] = {}
        for number, pdo in maps.items():
            if not pdo.enabled or not pdo.map:
                continue
            issue = transmission_type_issue(kind, pdo.trans_type)
            if issue is not None:
                raise CanopenError(
                    f"node {want.node_id} ({want.label}): {kind}{number} (COB-ID 0x{pdo.cob_id:03X}) has {issue}"
                )
            start = sum(size for _, _, size in slices)
            bit = 0
            for var in pdo.map:
                if bit % 8 == 0:
                    found[(var.index, var.subindex)] = (start + bit // 8, var.length)
                bit += var.length
            size = (bit + 7) // 8
            slices.append((pdo.cob_id, start, size))
            if pdo.on_message in network.subscribers.get(pdo.cob_id, []):
                network.unsubscribe(pdo.cob_id, pdo.on_message)  # canopen's own decoding: not needed
        offsets: list[int | None] = []
        for index, subindex, bits in objects:
            place = found.get((index, subindex))
            if place is not None and place[1] != bits:
                raise CanopenError(
                    f"node {want.node_id} ({want.label}): 0x{index:04X} is mapped with {place[1]} bits "
                    f"in a {kind}, a CiA 402 drive has {bits}"
                )
            if place is None and index in REQUIRED:
                raise CanopenError(
                    f"node {want.node_id} ({want.label}): 0x{index:04X} is in no {kind}: a CiA 402 drive must map it"
                )
            offsets.append(None if place is None else place[0])
        return offsets

    def _units(self) -> list[DriveUnits]:
        defaults = self.options.drive_defaults
        return [defaults.units(n.counts_per_rev, n.gear_ratio, n.rated_torque) for n in self.options.nodes]

    def _link(self, offsets: list[list[int]]) -> None:
        opts, view = self.options, self.view
        specs = []
        for node_opts, units in zip(opts.nodes, self._units(), strict=True):
            specs.append(
                DriveSpec(
                    node_opts.label,
                    node_opts.joint,
                    view.joint_names.index(node_opts.joint),
                    units,
                    node_opts.position_offset,
                )
            )
        stuck = max(1, round(opts.stuck_after_ms * 1e6 / self._cycle_ns()))
        self.drives = DriveGroup.on_buffers(self._inputs, self._outputs, offsets, specs, stuck_after=stuck)
        self.drives.bind_state(view.state)

    # ------------------------------------------------------------ callbacks of the received frames

    def _tpdo_callback(self, target: memoryview, size: int):
        def on_tpdo(can_id: int, data: bytearray, timestamp: float) -> None:
            if len(data) != size:
                self.malformed += 1
                self._warn.warning(
                    f"dlc{can_id}",
                    "canopen %s: TPDO 0x%03X of %d bytes, %d expected: dropped",
                    self.name,
                    can_id,
                    len(data),
                    size,
                )
                return
            target[:] = data
            self.rx_tpdos += 1

        return on_tpdo

    def _heartbeat_callback(self, k: int):
        heard = self._heard

        def on_heartbeat(state: int) -> None:
            heard[k] = time.monotonic()

        return on_heartbeat

    def _emcy_callback(self, k: int):
        def on_emcy(error) -> None:
            self._emcy.append((k, error.code, error.register))

        return on_emcy

    # ------------------------------------------------------------ cycles off the tick

    def _cycle_holding(self) -> None:
        """One cycle with every drive held where it stands (bring-up, close); lock held."""
        drives = cast(DriveGroup, self.drives)  # cycled only when the bus has drives
        drives.decode(0, 0, into_state=False)
        drives.update_machines(self._on_drive_event)
        drives.write_holding()
        self._send_cycle()

    def _bringup_wait(self) -> None:
        """Bring-up cycles the bus itself, a cycle a period."""
        with self._lock:
            self._cycle_holding()
        time.sleep(self._cycle_ns() * 1e-9)

    def _not_enabled_error(self, timeout_s: float) -> Exception:
        if self._estop_requested:
            return CanopenError("emergency stop during bring-up: the drives were not enabled")
        return CanopenError(f"drives not enabled within {timeout_s:g} s: {self._not_enabled()}")

    def _send_cycle(self) -> None:
        out = self._out_view
        # on the tick: no check added. The bus is opened by bring-up before any cycle is sent
        # and closed only after the last one.
        send = self.bus.send  # type: ignore[union-attr]
        errors = self.tx_errors
        for msg, start, end in self._rpdos:
            msg.data[:] = out[start:end]
            try:
                send(msg, 0)
                self.tx_frames += 1
            except can.CanError as exc:
                self.tx_errors += 1
                self._warn.warning("tx", "canopen %s: sending 0x%03X failed: %s", self.name, msg.arbitration_id, exc)
        try:
            send(self._sync, 0)
            self.tx_frames += 1
        except can.CanError as exc:
            self.tx_errors += 1
            self._warn.warning("tx", "canopen %s: sending SYNC failed: %s", self.name, exc)
        self._failed_cycles = self._failed_cycles + 1 if self.tx_errors != errors else 0

    # ------------------------------------------------------------ the tick

    async def read(self) -> None:
        view = self.view
        clock = view.clock
        now = time.monotonic()
        if now - self._last_read_s > self._heartbeat_check_s * 5:  # half the timeout without a read
            # this process did not run (frozen, a host stall): the nodes' silence since is not
            # theirs to answer for; each gets a whole timeout from now, as the watchdog process
            # counts from its own late wake-up
            np.maximum(self._heard, now, out=self._heard)
        self._last_read_s = now
        if now >= self._next_heartbeat_check:  # every tenth of the timeout: a numpy call, not per tick
            self._next_heartbeat_check = now + self._heartbeat_check_s
            heard = self._heard
            if heard.size and now - heard.min() > self.options.heartbeat_timeout_ms * 1e-3:
                self._lost(now)
        if self._emcy:
            self._handle_emergencies()
        if self.bus_off or self._failed_cycles >= self.options.tx_error_limit or self._rx_error is not None:
            self._bus_failed()
        if self.gateway is not None:
            self.gateway.read(clock.tick, clock.now_ns, view)
        drives = self.drives
        if drives is None:  # a bus of sensors only
            view.fresh_tick = clock.tick
            return
        if not self._written and self._active:
            # the loop commands nothing (emergency stop, disabled): the drives still get their
            # cycles, held where they stand (a quick stop ramps, a released drive is enabled)
            with self._lock:
                self._cycle_holding()
        self._written = False
        got = self.rx_tpdos - self._seen
        self._seen += got
        if got < self._tpdos_per_cycle:
            self.late_cycles += 1
            return
        with self._lock:
            drives.decode(clock.tick, clock.now_ns)
            drives.update_machines(self._on_drive_event)
        view.fresh_tick = clock.tick

    async def write(self) -> None:
        with self._lock:
            if self._estop_sent:
                return
            if self.drives is not None:
                self.drives.write(self.view.command)
            self._send_cycle()
        self._written = True
        self.cycles += 1

    def _bus_failed(self) -> None:
        opts = self.options
        if self._rx_error is not None:
            raise CanopenError(
                f"{opts.interface}:{opts.channel}: receiving failed {RX_FAILURES_LIMIT} times in a row: "
                f"{self._rx_error}"
            )
        if self.bus_off:
            raise CanopenError(
                f"{opts.interface}:{opts.channel} is bus-off (an error frame said so): no frame reaches the drives"
            )
        raise CanopenError(
            f"{opts.interface}:{opts.channel}: {self._failed_cycles} cycles in a row could not send "
            f"their frames ({self.tx_errors} frames in all): bus-off, no ACK or the interface down"
        )

    def _lost(self, now: float) -> None:
        silent = [
            self.options.nodes[k] for k in np.flatnonzero(now - self._heard > self.options.heartbeat_timeout_ms * 1e-3)
        ]
        self.lost_nodes = [n.label for n in silent]
        for node in silent:
            self.view.state.fault[self.view.joint_names.index(node.joint)] |= Fault.HARDWARE
        raise CanopenError(
            "heartbeat lost: "
            + ", ".join(
                f"node {n.node_id} ({n.label}, joint {n.joint}) silent for more than {self.options.heartbeat_timeout_ms:g} ms"
                for n in silent
            )
        )

    def _handle_emergencies(self) -> None:
        while self._emcy:  # popleft: an EMCY the notifier appends meanwhile is taken too, never lost
            k, code, register = self._emcy.popleft()
            node = self.options.nodes[k]
            self._last_emcy[k] = code
            if code == 0:
                log.info("canopen %s: node %d (%s): error reset", self.name, node.node_id, node.label)
                continue
            self.emergencies += 1
            machine = self.drives.machines[k] if self.drives is not None else None
            if machine is not None and machine.faulted and not machine.error_code:
                machine.error_code = code  # the fault came first (its TPDO, or the EMCY a cycle late)
            self.view.fault(
                f"joint {node.joint}: emergency (EMCY) from node {node.node_id} ({node.label}): "
                f"error code 0x{code:04X}, {describe_error_code(code)}; error register 0x{register:02X} "
                f"({describe_error_register(register)})",
                hold=False,
            )

    def _on_drive_event(self, i: int, event: DriveEvent) -> None:
        if not self._active:  # bring-up: what does not come up is reported by open()
            log.debug("canopen %s: %s", self.name, event)  # the enable sequence: four lines a drive
            return
        drives = cast(DriveGroup, self.drives)  # its own drives' state machines report events
        detail = ""
        if event.kind is EventKind.FAULT_ENTERED:
            machine = drives.machines[i]
            from_drive = machine.error_code  # 0x603F, when the drive maps it
            if self._emcy:  # an EMCY the notifier took after this read began: the fault's code
                self._handle_emergencies()
            if not from_drive and self._last_emcy[i]:  # 0x603F unmapped: the code the EMCY gave
                machine.error_code = self._last_emcy[i]
                detail = f" (EMCY error code 0x{machine.error_code:04X})"
            if machine.error_code:
                detail += f": {describe_error_code(machine.error_code)}"
        self._respond(i, event, detail)

    # ------------------------------------------------------------ application API

    def _remote(self, node: int | str) -> canopen.RemoteNode:
        for k, n in enumerate(self.options.nodes):
            if node in (n.node_id, n.label, n.joint):
                return self.remotes[k]
        raise CanopenError(f"no node {node!r} on this bus")

    async def sdo_read(self, node: int | str, index: int, subindex: int = 0) -> bytes:
        """Upload an object by SDO, in a worker thread (never on the tick)."""
        remote = self._remote(node)
        return await asyncio.to_thread(remote.sdo.upload, index, subindex)

    async def sdo_write(self, node: int | str, index: int, subindex: int, data: bytes) -> None:
        """Download an object by SDO, in a worker thread (never on the tick)."""
        remote = self._remote(node)
        await asyncio.to_thread(remote.sdo.download, index, subindex, bytes(data))

    # ------------------------------------------------------------ safety and shutdown

    def _bus_ready(self) -> bool:
        return self.bus is not None

    def _send_holding(self) -> None:
        cast(DriveGroup, self.drives).write_holding()  # estop sends only when the bus has drives
        self._send_cycle()

    def safe_actions(self) -> list:
        """An NMT Stop to every node (or ``estop_frame``), sent by the watchdog process on its
        own CAN_RAW socket. Only on socketcan: a ``virtual`` bus lives in this process (no
        other process can reach it), and the other interfaces' devices are held by this one."""
        if self.options.interface != "socketcan":
            return []
        return [SendCanFrame(self.options.channel, estop_can_frame(self.options.estop_frame))]

    async def close(self) -> None:
        self._remember_enabled()
        if self._reader is not None:  # the shutdown's cycles run in a thread: reception back to one
            self._stop_reader()
            if self.network is not None and self.bus is not None:
                self.network.notifier = can.Notifier(self.bus, self.network.listeners, self.network.NOTIFIER_CYCLE)
        await asyncio.to_thread(self._shutdown)

    def _shutdown(self, budget_s: float = 0.5) -> None:
        """Quick stop every drive and wait for it (the ramp), then disable it, within
        ``budget_s``; then every node to PRE-OPERATIONAL, and nothing sent any more."""
        try:
            if self.drives is not None and self.bus is not None:
                self._stop_drives(budget_s, self._cycle_ns() * 1e-9)
                for node in self.remotes:
                    node.nmt.send_command(0x80)
        except Exception as exc:
            log.warning("canopen %s: stopping the drives failed: %s", self.name, exc)
        finally:
            self._estop_requested = self._estop_sent = True
            if self.network is not None:
                self.network.disconnect()
            if self.sim is not None:
                self.sim.close()

    def health(self) -> dict[str, Any]:
        opts = self.options
        out: dict[str, Any] = {
            "bus": f"{opts.interface}:{opts.channel}",
            "nodes": len(opts.nodes),
            "cycles": self.cycles,
            "tx_frames": self.tx_frames,
            "tx_errors": self.tx_errors,
            "rx_tpdos": self.rx_tpdos,
            "malformed": self.malformed,
            "late_cycles": self.late_cycles,
            "error_frames": self.error_frames,
            "rx_errors": self.rx_errors,
            "reception": "loop" if self._reader is not None else "given up" if self._rx_error is not None else "thread",
            "emergencies": self.emergencies,
        }
        if self._frame_sizes:
            rate = 1e9 / self._cycle_ns()
            sensors = self.gateway.frame_sizes() if self.gateway is not None else []
            out["bus_load_configured_pct"] = round(
                100 * (busload.load(self._frame_sizes, rate, opts.bitrate) + busload.load_at(sensors, opts.bitrate)), 1
            )
            elapsed = (time.monotonic_ns() - self._started_ns) * 1e-9
            if self.cycles and elapsed > 0:
                achieved = busload.load(self._frame_sizes, self.cycles / elapsed, opts.bitrate)
                if self.gateway is not None:
                    achieved += self.gateway.bits / elapsed / opts.bitrate
                out["bus_load_pct"] = round(100 * achieved, 1)
        out.update(self._drives_health())
        if self.lost_nodes:
            out["lost"] = self.lost_nodes
        if self.gateway is not None:
            out["sensors"] = self.gateway.health()
        return out
