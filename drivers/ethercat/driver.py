"""``ethercat``: an EtherCAT master on pysoem, with CiA 402 drives, IMUs and F/T sensors.

Bring-up runs off the tick, in the driver's own thread: find the slaves, read each one's PDO
mapping over CoE, map the process data, set DC up, SAFEOP, every slave's SM watchdog time, a
valid process-data cycle, OP (the watchdogs read back: a slave that would not stop by itself
when this process stops is refused), then enable the drives with target = actual (bumpless).
Until the first tick a keep-alive thread cycles the bus so that no slave's watchdog trips.

Each tick, one frame carries every slave's process data. With ``exchange = "split"`` (the
default) ``write`` sends the frame with this tick's outputs and the next tick's ``read``
receives it: the frame has a whole period to come back and nobody waits for it. With
``"immediate"``, ``read`` sends the outputs of the previous tick and waits for the frame (the
inputs are as fresh as they can be; the tick pays the round trip, which is measured).

The working counter is checked every cycle against the driver's own sum (2 per slave with
outputs, 1 per slave with inputs, leaving out slaves known to be lost). A bad cycle keeps the
last inputs and does not refresh the joints. ``wkc_error_limit`` bad cycles in a row read
every slave's state (when one is out of OP, each slave again by a checked frame of its own:
a reply that came back late to an earlier frame can stand in for a one-frame read): a drive
that left OP fails the driver (the loop sends every driver its
emergency stop and the robot to its safe state); a lost sensor faults its device, the run goes
on without it, and it is brought back to OP step by step every ``recover_interval_s``.

A drive fault (CiA 402) faults its joint, is reported, and asks the loop to hold the robot;
:meth:`EthercatDriver.reset_faults` grants one fault reset, and the drive is re-enabled where
it stands (target = actual, the joint's command resynchronised by the loop).

SDOs (:meth:`sdo_read`, :meth:`sdo_write`) are awaitables that run in the driver's thread,
never on the tick. The driver opens only ``options.interface`` (SOEM sends raw broadcast
frames and sets the interface promiscuous).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, cast

import numpy as np
import pysoem  # the `ethercat` extra; a missing one is reported by the plugin loader

from aiohal.fieldbus.busvar import ProcessImage, UnknownVariableError, VariableTypeError
from aiohal.fieldbus.cia402 import DriveEvent, EventKind, Target
from aiohal.fieldbus.cia402_driver import Cia402Driver
from aiohal.logutil import RateLimitedLogger
from aiohal.robot import Fault

from .bus import (
    OP,
    SAFEOP,
    BringUpError,
    Bus,
    EthercatError,
    SlaveInfo,
    TransientBringUpError,
    check_identity,
    expected_wkc,
    shares_a_byte,
    state_name,
)
from .dc_lock import DcLock
from .devices import DriveGroup, DriveSpec, ForceTorqueDevice, ImuDevice
from .options import FT_CONTROL, FT_VARIABLES, IMU_VARIABLES, EthercatOptions, option_issues
from .sm_watchdog import Setting

log = logging.getLogger(__name__)

RING = 1 << 16  # per-cycle timings kept for the report (the last 65 s at 1 kHz)
#: cycles the health's percentiles are taken over, evenly spread over the ring: health is
#: sampled on the event loop between ticks, where the percentiles of the whole ring (two
#: partitions of 65 536 values, milliseconds) would make the next ticks late
HEALTH_SAMPLES = 4096


def _has_variable(image: ProcessImage, slave: str, name: str) -> bool:
    try:
        image.slave(slave).variable(name)
    except UnknownVariableError:
        return False
    return True


class EthercatDriver(Cia402Driver):
    Options = EthercatOptions
    bus_name = "ethercat"
    device_kinds = frozenset({"imu", "force_torque"})
    options: EthercatOptions

    @classmethod
    def check_config(cls, options, joints, devices, robot):
        return option_issues(options, joints, devices)

    def __init__(self, name, view, options) -> None:
        super().__init__(name, view, options)
        self.bus = self._new_bus()  # opens nothing: open() does, on a fresh one per attempt
        self._executor: ThreadPoolExecutor | None = None  # the driver's own thread, from open() on
        self._loop_thread = threading.get_ident()
        self._init_state()

    # ------------------------------------------------------------ lifecycle

    async def open(self) -> None:
        opts = self.options
        if opts.frame_timeout_us is not None:
            pysoem.settings.timeouts.ret = opts.frame_timeout_us
        self._executor = executor = ThreadPoolExecutor(1, thread_name_prefix=f"ethercat-{self.name}")
        loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        first: BaseException | None = None
        for attempt in range(1, opts.bringup_attempts + 1):
            self._init_state()
            self.bus = self._new_bus()
            try:
                await loop.run_in_executor(executor, self._bring_up)
                return
            except BaseException as exc:
                self._stop_keepalive(raise_error=False)
                await loop.run_in_executor(executor, self._shutdown)
                # a frame lost in a stall (an SII or mailbox read, a state change) fails a
                # bring-up that works the next time; a configuration error fails every attempt,
                # and the first error is the one that says why
                if first is None:
                    first = exc
                elif exc is not first:
                    log.warning("ethercat %s: bring-up attempt %d failed too: %s", self.name, attempt, exc)
                    raise first  # noqa: B904 - the first failure is the one to report (chained to this one)
                if not (
                    attempt < opts.bringup_attempts
                    and not self._estop_requested
                    and isinstance(exc, (TransientBringUpError, *self.bus.lost_frame))
                ):
                    raise
                log.warning("ethercat %s: bring-up attempt %d failed (%s), trying again", self.name, attempt, exc)

    def _new_bus(self) -> Bus:
        opts = self.options
        return Bus(pysoem, opts.interface, overlap=opts.overlap_map, take_over=opts.take_over)

    def _init_state(self) -> None:
        """Everything a bring-up attempt starts from (the counters included)."""
        period_ns = self.view.clock.period_ns
        self._init_drive_state()  # the drives, the lock on the cyclic frame and their state, no estop
        self._activated = False  # the first read (activation) was done
        self._in_op = False  # every slave reached OP: the drives apply outputs, their machines run
        self._outstanding = False  # a cyclic frame was sent and not yet received
        self._written = False  # write() packed this tick's outputs (the loop skips write in ESTOP)
        self._last_tick_ns = 0  # when a tick last cycled the bus (monotonic)
        self._keepalive_after_ns = max(int(self.options.keepalive_after_ms * 1e6), 3 * period_ns)
        self._keepalive: threading.Thread | None = None
        self._keepalive_stop = threading.Event()
        self._keepalive_error: BaseException | None = None
        self._keepalive_cycles = 0
        self._wake = threading.Event()  # the keep-alive thread: stop, or an AL state check is due
        self._al_every = max(1, round(self.options.al_check_interval_ms * 1e6 / period_ns))  # in bus cycles
        self._al_next = 0  # the bus cycle at which write() asks for the next AL state check
        self._al_due = False
        self._al_found: tuple[int, list[tuple[int, int]]] | None = None  # (generation, read) off the tick, one not OP
        self._states_generation = 0  # the tick's own state reads: a check read before one of them is stale
        self.al_checks = 0
        self.al_checks_unanswered = 0  # of which some slave did not answer in time (a busy host): not judged
        self.states_unanswered = 0  # checked state reads no slave answered (frames lost): not judged
        self._pending: list[tuple[int, DriveEvent]] = []  # drive events seen off the loop's thread
        self.infos: list[SlaveInfo] = []
        self.dc_lock: DcLock | None = None  # options.dc_lock, from the bring-up on
        self.sm_watchdogs: dict[str, float] = {}  # slave name -> its SM watchdog time (ms), read back after OP
        self.image: ProcessImage | None = None
        self.sensors: list[tuple[int, ImuDevice | ForceTorqueDevice]] = []
        self._taring: list[ForceTorqueDevice] = []  # F/T sensors with a tare under way
        self.lost: set[int] = set()
        self._unrecoverable: set[int] = set()  # lost below SAFEOP: reported, not recovered in the tick
        self._reported: set[int] = set()  # lost slaves already reported
        self._expected = 0
        self._known: list[int] = []  # each slave's AL state as last read (OP until one is read otherwise)
        self._bad_run = 0
        self._check_states = False  # read every slave's state at the next read (a drive dropped out)
        self._next_recover = 0.0
        self.cycles = 0
        self.wkc_errors = 0  # cycles without the expected working counter...
        self.frames_lost = 0  # ...of which no frame came back in time (the others: a slave short)
        self.diagnoses = 0
        self.recovered = 0
        self.emergencies = 0
        self._rtt_ns = np.zeros(RING, dtype=np.int64)
        self._cpu_ns = np.zeros(RING, dtype=np.int64)
        self._read_cpu = 0
        self._warn = RateLimitedLogger(log)

    def _bring_up(self) -> None:
        """Blocking: from nothing to OP with the drives enabled; runs in the driver's thread."""
        opts, bus = self.options, self.bus
        found = bus.open()
        if found != len(opts.slaves):
            names = ", ".join(f"{i}: {s.name}" for i, s in enumerate(bus.slaves)) or "none"
            raise BringUpError(
                f"found {found} slave(s) on {opts.interface!r} ({names}), options.slaves lists {len(opts.slaves)}"
            )
        for i, (s, slave) in enumerate(zip(opts.slaves, bus.slaves, strict=True)):  # before any mailbox traffic
            check_identity(i, slave.name, s.name, slave.man, slave.id, s.vendor_id, s.product_code)
        bus.watch_emergencies(self._on_emergency)
        for i, s in enumerate(opts.slaves):  # remapped in PREOP, then read back like any mapping
            for assign, pdos in s.pdo_assignments():
                bus.write_pdo_assignment(i, assign, pdos)
        layouts = [bus.read_layout(i, s.names) for i, s in enumerate(opts.slaves)]
        for i, layout in enumerate(layouts):
            if shares_a_byte(layout):
                raise BringUpError(
                    f"slave {i} ({bus.slaves[i].name}) has {layout.output_bits} output and {layout.input_bits} input "
                    "bits: SOEM packs a slave of fewer than 8 bits into a byte it shares with its neighbours, "
                    "which this driver does not support (pysoem reads and writes whole bytes per slave)"
                )
        bus.map(
            opts.dc,
            sync0=opts.sync0_slaves(),
            cycle_ns=self.view.clock.period_ns,
            shift_ns=round(opts.sync0_shift_us * 1000),
            safeop_timeout_s=opts.safeop_timeout_s,
            static_frames=opts.dc_static_frames,
        )
        for i, (s, layout, slave) in enumerate(zip(opts.slaves, layouts, bus.slaves, strict=True)):
            self.infos.append(
                SlaveInfo(
                    i, s.name, slave.name, slave.man, slave.id, slave.rev, layout, len(slave.output), len(slave.input)
                )
            )
        # known from here on, so that a bring-up failing after the mapping reports it
        self._expected = expected_wkc(self.infos)
        self._known = [OP] * len(self.infos)
        written = self._program_watchdogs()
        self.image = image = ProcessImage([(s.name, layout) for s, layout in zip(opts.slaves, layouts, strict=True)])
        for info in self.infos:
            image.slave(info.name).check_sizes(info.output_bytes, info.input_bytes)
        self._link_devices()
        if self._expected != self.bus.master.expected_wkc:
            log.info(
                "ethercat %s: expected working counter %d (pysoem says %d)",
                self.name,
                self._expected,
                self.bus.master.expected_wkc,
            )
        # inputs are copied in image order with one join; outputs sliced per slave
        by_input = sorted((i for i in self.infos if i.input_bytes), key=lambda i: image.slave(i.name).input_offset)
        # pysoem's property getters/setters, bound once: a property lookup per slave per cycle costs more
        self._in_getters = [bus.slaves[i.position]._get_input for i in by_input]
        self._in_parts = [(i.position, bus.slaves[i.position], image.slave(i.name)) for i in by_input]
        self._contiguous_inputs = sum(i.input_bytes for i in by_input) == len(image.inputs)
        self._inputs_bytes = image.inputs.data.cast("B")  # bytes in with a memcpy, no numpy call
        self._out_parts = [
            (
                bus.slaves[i.position]._set_output,
                image.slave(i.name).output_offset,
                image.slave(i.name).output_offset + i.output_bytes,
            )
            for i in self.infos
            if i.output_bytes
        ]
        self._send_now, self._receive_now = bus.cyclic_calls(opts.receive_timeout_us)
        if opts.dc and opts.dc_lock:
            period = self.view.clock.period_ns
            target = (round(opts.sync0_shift_us * 1000) - period // 2) % period  # half a cycle before SYNC0
            self.dc_lock = DcLock(bus.master, self._send_now, self._receive_now, self.view.clock, target)
            self._send_now, self._receive_now = self.dc_lock.send, self.dc_lock.receive
        self._split = opts.exchange == "split"
        self._on_event = self._on_drive_event  # bound once, not on every read
        period_s = self.view.clock.period_ns * 1e-9
        bus.request_op(self._bringup_cycle, opts.op_timeout_s, period_s)
        self._in_op = True
        log.info(
            "ethercat %s: %d slave(s) in OP on %s, %d B out / %d B in",
            self.name,
            len(self.infos),
            opts.interface,
            len(image.outputs),
            len(image.inputs),
        )
        self._start_keepalive(period_s)
        for i, setting in written.items():  # (the keep-alive feeds the watchdogs meanwhile)
            self.sm_watchdogs[opts.slaves[i].name] = bus.check_pd_watchdog(i, setting).ms
        if self.drives is not None and opts.enable_on_open:
            self._wait_enabled(opts.enable_timeout_s)

    def _program_watchdogs(self) -> dict[int, Setting]:
        """Every slave with outputs gets ``sm_watchdog_ms`` (in SAFEOP); what each holds, by
        position, to be checked after OP. With 0, none is set and a warning says so."""
        bus, ms = self.bus, self.options.sm_watchdog_ms
        with_outputs = [i for i, slave in enumerate(bus.slaves) if len(slave.output)]
        if ms == 0:
            if with_outputs:
                log.warning(
                    "ethercat %s: sm_watchdog_ms = 0: the SM watchdogs of slave(s) %s are left as they are "
                    "and not checked; a slave whose own is off keeps its outputs when this process stops",
                    self.name,
                    ", ".join(f"{i} ({self.options.slaves[i].name})" for i in with_outputs),
                )
            return {}
        return {i: bus.program_pd_watchdog(i, ms) for i in with_outputs}

    def _link_devices(self) -> None:
        opts, image, view = self.options, self.image, self.view
        assert image is not None
        specs = []
        defaults = opts.drive_defaults
        for i, s in enumerate(opts.slaves):
            if s.kind == "cia402":
                units = defaults.units(s.counts_per_rev, s.gear_ratio, s.rated_torque)
                joint = cast(str, s.joint)  # check_config: every cia402 slave names its joint
                specs.append(DriveSpec(s.name, joint, view.joint_names.index(joint), units, s.position_offset))
            elif s.kind == "imu":
                device = cast(str, s.device)  # check_config: every sensor slave names its device
                self.sensors.append(
                    (i, ImuDevice(image, s.name, view.devices[device], {**IMU_VARIABLES, **s.variables}))
                )
            elif s.kind == "force_torque":
                control = s.variables.get("control")  # named: must exist; else the default if mapped
                if control is None and _has_variable(image, s.name, FT_CONTROL):
                    control = FT_CONTROL
                variables = {k: v for k, v in {**FT_VARIABLES, **s.variables}.items() if k != "control"}
                device = cast(str, s.device)
                self.sensors.append((i, ForceTorqueDevice(image, s.name, view.devices[device], variables, control)))
        if sorted(s.row for s in specs) != list(range(view.dof)):  # check_config says so; decode relies on it
            raise BringUpError(
                f"every joint of an ethercat driver needs one cia402 drive: joints "
                f"{list(view.joint_names)}, drives for {[s.joint for s in specs]}"
            )
        if specs:
            stuck = max(1, round(opts.stuck_after_ms * 1e6 / self.view.clock.period_ns))
            target = Target.ENABLED if opts.enable_on_open and not self._estop_requested else Target.DISABLED
            self.drives = DriveGroup(image, specs, stuck_after=stuck, target=target)
            self.drives.bind_state(self.view.state)
            if self._estop_requested:
                self.drives.request(Target.QUICK_STOP)

    # ------------------------------------------------------------ cycling off the tick (driver's threads)

    def _bringup_cycle(self, timeout_us: int | None = None) -> int:
        """One blocking exchange, every drive held where it stands; the caller holds the lock
        (or no tick can run yet). Returns the working counter."""
        bus = self.bus
        if self._outstanding:  # a frame of the tick's is still out: take it first
            self._count_off_tick(bus.receive(self.options.receive_timeout_us))
            self._outstanding = False
        self._pack_outputs_holding()
        bus.send()
        wkc = bus.receive(timeout_us or self.options.bringup_receive_timeout_us)
        self._count_off_tick(wkc)
        if wkc == self._expected:
            self._load_inputs()
            if self.drives is not None:
                self.drives.decode(0, 0, into_state=False)  # the robot's state is the loop's
                if self._in_op:  # before OP a drive ignores its outputs: a fault reset would be spent
                    self.drives.update_machines(self._on_drive_event)
        return wkc

    def _count_off_tick(self, wkc: int) -> None:
        """A running bus's cycle the keep-alive ran (a stall of the loop) counts in the health
        as the tick's own: a working-counter error there is one all the same."""
        if self._activated and wkc != self._expected:
            self.wkc_errors += 1
            if wkc < 0:
                self.frames_lost += 1

    def _pack_outputs_holding(self) -> None:
        if self.drives is not None:
            self.drives.write_holding()
        self._write_outputs()

    def _start_keepalive(self, period_s: float) -> None:
        """A thread that cycles the bus whenever the loop does not (before the first tick,
        between runs, in a stall), so that no slave's watchdog trips: every drive is then held
        where it stands. While the loop ticks it only wakes every ``keepalive_after_ms / 2``."""
        self._keepalive_stop.clear()
        ready = threading.Event()
        check_s = self._keepalive_after_ns / 2e9
        running_timeout_us = max(2 * self.view.clock.period_ns // 1000, self.options.receive_timeout_us)

        al_every_s = self.options.al_check_interval_ms / 1e3
        wake = self._wake

        def run() -> None:
            try:
                deadline = next_al = time.monotonic()
                while not self._keepalive_stop.is_set():
                    if time.monotonic_ns() - self._last_tick_ns < self._keepalive_after_ns:
                        ready.set()
                        wake.wait(check_s)  # set by write() when an AL state check is due
                        wake.clear()
                        if self._al_due:
                            self._al_due = False
                            self._check_al_states()
                        deadline = next_al = time.monotonic()
                        continue
                    with self._lock:
                        self._bringup_cycle(running_timeout_us if self._activated else None)
                        self._keepalive_cycles += 1
                    ready.set()
                    if self._activated and time.monotonic() >= next_al:
                        next_al = time.monotonic() + al_every_s
                        self._check_al_states()
                    deadline += period_s
                    time.sleep(max(0.0, deadline - time.monotonic()))
            except BaseException as exc:  # reported by the next read, or by open
                self._keepalive_error = exc
                ready.set()

        self._keepalive = threading.Thread(target=run, name=f"ethercat-{self.name}-keepalive", daemon=True)
        self._keepalive.start()
        ready.wait(5.0)

    def _stop_keepalive(self, raise_error: bool = True) -> None:
        thread, self._keepalive = self._keepalive, None
        if thread is not None:
            self._keepalive_stop.set()
            self._wake.set()
            thread.join(2.0)
        self._raise_keepalive_error(raise_error)

    def _raise_keepalive_error(self, raise_error: bool = True) -> None:
        if self._keepalive_error is not None:
            exc, self._keepalive_error = self._keepalive_error, None
            if raise_error:
                raise EthercatError(f"cycling the bus between ticks failed: {exc}") from exc
            log.warning("ethercat %s: cycling the bus between ticks failed: %s", self.name, exc)

    def _bringup_wait(self) -> None:
        """The keep-alive thread cycles the bus meanwhile: a pause, or the error that stopped it."""
        if self._keepalive_error is not None:
            self._stop_keepalive()  # raises it
        time.sleep(0.005)

    def _not_enabled_error(self, timeout_s: float) -> Exception:
        """The keep-alive thread stopped first (its error, if any, is the one raised)."""
        self._stop_keepalive()
        if self._estop_requested:
            return BringUpError("emergency stop during bring-up: the drives were not enabled")
        # a drive still in Fault after its reset would be in Fault again; a slow one may not be
        drives = cast(DriveGroup, self.drives)  # bring-up waits only when the bus has drives
        error = BringUpError if any(m.faulted for m in drives.machines) else TransientBringUpError
        return error(f"drives not enabled within {timeout_s:g} s: {self._not_enabled()}")

    # ------------------------------------------------------------ the tick

    async def read(self) -> None:
        # the tick's path is spelled out here (inputs, drives, sensors): on a tick that starts
        # on cold caches each helper's frame costs more than its lines (about 4 µs per cycle
        # with 7 drives, measured alternately against the factored version)
        perf = time.perf_counter_ns
        t0 = perf()
        if self._keepalive_error is not None:
            self._raise_keepalive_error()
        with self._lock:
            if not self._activated:
                self._activate()
                t0 = perf()
            if not self._outstanding:
                if not self._written:  # the loop commands nothing (emergency stop), or a keep-alive cycled
                    self._pack_outputs_holding()
                self._send_now()
            self._written = False
            sent = perf()
            wkc = self._receive_now()
            received = perf()
            self._outstanding = False
            self._last_tick_ns = time.monotonic_ns()
            cycles = self.cycles = self.cycles + 1
            # immediate: the round trip; split: what was left of it after a whole tick
            self._rtt_ns[cycles & (RING - 1)] = received - sent
            if self._pending:
                self._handle_pending()
            if wkc == self._expected:  # a good cycle: inputs into the image, then into the robot's records
                if self._bad_run:
                    self._bad_run = 0
                lost = self.lost
                if self._contiguous_inputs and not lost:
                    self._inputs_bytes[:] = b"".join([get() for get in self._in_getters])
                else:
                    self._load_inputs()
                view = self.view
                clock = view.clock
                tick, now_ns = clock.tick, clock.now_ns
                drives = self.drives
                if drives is not None:
                    drives.decode(tick, now_ns)  # straight into the state's rows, each stamped (every joint is a drive)
                    drives.update_machines(self._on_event)  # after the rows: a resync sees this cycle's position
                for position, sensor in self.sensors:
                    sensor.read(tick, now_ns, position in lost)
                view.fresh_tick = tick  # DriverView.mark_fresh(stamp_rows=False): the decode stamped the rows
            else:
                self.wkc_errors += 1
                if wkc < 0:  # no frame back within receive_timeout_us (SOEM's EC_NOFRAME)
                    self.frames_lost += 1
                self._bad_run += 1
                if self._bad_run >= self.options.wkc_error_limit:
                    self._diagnose(wkc)
            if self._check_states:  # a slave in SAFEOP still counts in the working counter
                self._check_states = False
                self._diagnose(wkc)
            if self._al_found is not None:
                (generation, found), self._al_found = self._al_found, None
                if generation == self._states_generation:
                    self._judge(found, f"AL state check (working counter {wkc}/{self._expected})")
            if self.lost and time.monotonic() >= self._next_recover:
                self._recover_lost()
        self._read_cpu = (perf() - t0) - (received - sent)

    def _activate(self) -> None:
        """The activation read (lock held): a good cycle is required, so that the loop starts
        its commands from where the joints really are, and every drive asked to be enabled is."""
        wkcs = []
        for _ in range(3):
            wkcs.append(self._bringup_cycle())
            if wkcs[-1] == self._expected:
                break
        else:
            why = "no frame came back" if max(wkcs) < 0 else self._states_not_op()
            raise EthercatError(
                f"no good process-data cycle at activation (working counters {wkcs}, expected {self._expected}): {why}"
            )
        if self.drives is not None and self.options.enable_on_open and not self.drives.all_enabled():
            raise EthercatError(f"drives not enabled at activation: {self._not_enabled()}")
        self._written = False
        self._activated = True

    def _states_not_op(self) -> str:
        try:
            self.bus.states()
        except Exception as exc:  # the reason we were asked for matters more than this failure
            return f"the slaves' states could not be read ({exc})"
        return self.bus.describe_not_in(OP)

    def _load_inputs(self) -> None:
        """Every slave's inputs into the image (read() does the usual case itself)."""
        if self._contiguous_inputs and not self.lost:
            self._inputs_bytes[:] = b"".join([get() for get in self._in_getters])
            return
        lost = self.lost
        for position, slave, part in self._in_parts:
            if position not in lost:
                part.load_inputs(slave.input)

    async def write(self) -> None:
        perf = time.perf_counter_ns
        t0 = perf()
        with self._lock:
            drives = self.drives
            if drives is not None:
                drives.write(self.view.command)
            if self._taring:
                self._advance_tares()
            # open() made the image; no test added to the tick
            out = self.image.outputs.tobytes()  # type: ignore[union-attr]  # _write_outputs, spelled out as in read()
            for set_output, start, end in self._out_parts:
                set_output(out[start:end])
            self._written = True
            if self._split and not self._outstanding:
                self._send_now()
                self._outstanding = True
            if self.cycles >= self._al_next:  # the AL states, read while the loop waits for its next tick
                self._al_next = self.cycles + self._al_every
                self._al_due = True
                self._wake.set()
        self._cpu_ns[self.cycles & (RING - 1)] = self._read_cpu + perf() - t0

    def _advance_tares(self) -> None:
        for sensor in self._taring:
            sensor.write_control()
        self._taring = [sensor for sensor in self._taring if sensor.tare_left > 0]

    def _write_outputs(self) -> None:
        out = self.image.outputs.tobytes()  # type: ignore[union-attr]  # open() made the image
        for set_output, start, end in self._out_parts:
            set_output(out[start:end])

    # ------------------------------------------------------------ events and bus errors

    def _on_drive_event(self, i: int, event: DriveEvent) -> None:
        if not self._activated:  # bring-up: open() and the activation read report what does not come up
            log.debug("ethercat %s: %s", self.name, event)  # the enable sequence: four lines a drive
            return
        if threading.get_ident() != self._loop_thread:  # the keep-alive thread: the loop's next read handles it
            self._pending.append((i, event))
            return
        if event.kind is EventKind.LOST_ENABLED:
            self._check_states = True  # its slave may have left OP (SM watchdog): that fails the driver
        self._respond(i, event)

    def _handle_pending(self) -> None:
        pending, self._pending = self._pending, []
        for i, event in pending:
            self._on_drive_event(i, event)

    def _on_emergency(self, position: int, emcy: Any) -> None:
        """An EMCY message (during an SDO); never raises."""
        self.emergencies += 1
        self._warn.warning(
            f"emcy{position}",
            "ethercat %s: emergency from slave %d (%s): error code 0x%04X, register 0x%02X",
            self.name,
            position,
            self.options.slaves[position].name,
            getattr(emcy, "error_code", 0),
            getattr(emcy, "error_reg", 0),
        )

    def _diagnose(self, wkc: int) -> None:
        """``wkc_error_limit`` bad cycles in a row (or a drive that left Operation enabled):
        which slaves are not in OP?"""
        self.diagnoses += 1
        self._bad_run = 0
        expected = self._expected  # the failing cycle's, before the states change it
        read = self._read_states(frames_back=wkc >= 0)
        if read is None:  # judged after the next bad run, if there is one
            return
        if wkc != expected and all(st == OP for st, _ in read):
            self._warn.warning(
                "wkc", "ethercat %s: working counter %d instead of %d, every slave in OP", self.name, wkc, expected
            )
        self._judge(read, f"working counter {wkc}/{expected}")

    def _read_states(self, frames_back: bool) -> list[tuple[int, int]] | None:
        """Every slave's (AL state, AL status code), in the tick: SOEM's one-frame read when it
        finds every slave in OP (one frame); else each slave by a checked frame of its own
        (bus.checked_states: a one-frame read may be another frame's bytes). A slave silent
        on its own frame is gone (NONE) when the cyclic frames come back (``frames_back``: the
        silence is the slave's); when they are being lost, what was known of it stays. None
        when no slave answered: nothing is judged."""
        states = self.bus.states()
        if all(st == OP for st in states):
            return [(OP, 0)] * len(states)
        found = self.bus.checked_states(range(len(states)))
        if all(entry is None for entry in found.values()):
            self.states_unanswered += 1
            self._warn.warning(
                "unanswered", "ethercat %s: no slave answered the state read; judged on a later read", self.name
            )
            return None
        silent = (0, 0) if frames_back else None
        return [found[i] or silent or (self._known[i], 0) for i in range(len(states))]

    def _check_al_states(self) -> None:
        """Off the tick (the keep-alive thread): every slave's AL state. A slave that dropped to
        SAFEOP (+ERROR) keeps its SyncManagers, so the working counter does not show it; the
        loop's next read() judges what this finds. ``read_state`` holds the GIL for one frame
        (two when states differ), so it runs right after write(), while the loop waits; a
        slave not yet lost that it finds out of OP is read again by a checked frame of its own
        (one more frame each; the first silent one ends the check). The lost slaves are their
        recovery's, each second, until every slave reads OP again."""
        generation = self._states_generation
        lost = self.lost
        try:
            self.al_checks += 1
            states = self.bus.states()
            # no answer in time (SOEM then reads NONE): a slave really gone shows in the working counter
            if any(st == 0 for i, st in enumerate(states) if i not in lost):
                self.al_checks_unanswered += 1
                return
            out = [i for i, st in enumerate(states) if st != OP and i not in lost]
            found = self.bus.checked_states(out, until_silent=True) if out else {}
        except Exception as exc:  # a frame lost: the next check reads again
            self._warn.warning("alcheck", "ethercat %s: reading the AL states failed: %s", self.name, exc)
            return
        answered = [entry for entry in found.values() if entry is not None]
        if len(answered) < len(found):  # as above, on its own frame
            self.al_checks_unanswered += 1
            return
        if any(state != OP for state, _ in answered):  # a slave out of OP, on its own frame
            self._al_found = (
                generation,
                [found.get(i) or ((self._known[i], 0) if i in lost else (OP, 0)) for i in range(len(states))],
            )
        elif lost and all(st == OP for st in states):  # every slave in OP again, the lost ones too
            self._al_found = (generation, [(OP, 0)] * len(states))

    def _judge(self, read: list[tuple[int, int]], why: str) -> None:
        """States read, (AL state, AL status code) each: a drive out of OP fails the driver,
        another slave is lost (reported with its AL status code, recovered step by step)."""
        states = [st for st, _ in read]
        lost = {i for i, st in enumerate(states) if st != OP}
        self._update_lost(states, lost)
        if not lost:
            return
        describe = {
            i: f"slave {i} ({self.infos[i].name}) in {state_name(states[i])}, AL status 0x"
            f"{read[i][1]:04X} ({pysoem.al_status_code_to_string(read[i][1])})"
            for i in sorted(lost)
        }
        drives_lost = [i for i in sorted(lost) if self.options.slaves[i].kind == "cia402"]
        if drives_lost:
            joints = ", ".join(self.options.slaves[i].joint or "?" for i in drives_lost)
            raise EthercatError(f"{why}: drive(s) of joint(s) {joints} out of OP: " + "; ".join(describe.values()))
        new = lost - self._reported
        for i in sorted(new):
            self.view.fault(
                f"{describe[i]}: lost; the run goes on without it, "
                f"recovery every {self.options.recover_interval_s:g} s",
                hold=False,
            )
        self._reported = set(lost)
        if new:  # (a check finding it still lost does not put its recovery off)
            self._next_recover = time.monotonic() + self.options.recover_interval_s

    def _update_lost(self, states: list[int], lost: set[int]) -> None:
        """New states read: who is lost, who came back, and the working counter to expect (a
        slave in SAFEOP still counts: its SyncManagers work, only its application ignores outputs)."""
        self._states_generation += 1
        for i in sorted(self.lost - lost):
            self._recovered(i)
        self.lost = set(lost)
        self._known = list(states)
        self._expected = sum(info.wkc for info, st in zip(self.infos, states, strict=True) if st & 0x0F in (SAFEOP, OP))
        for position, sensor in self.sensors:
            if position in lost:
                sensor.record.set_fault(Fault.HARDWARE)

    def _recover_lost(self) -> None:
        """One quick recovery step for the lost slaves (in the tick: a checked read and at
        most one frame each); one silent on its read stays as it was known."""
        self._next_recover = time.monotonic() + self.options.recover_interval_s
        found = self.bus.recover_steps(sorted(self.lost))
        states = list(self._known)
        for i, read in found.items():
            if read is not None:
                states[i] = read[0]
        lost = {i for i in self.lost if states[i] != OP}
        for i in sorted(lost - self._unrecoverable):
            if states[i] & 0x0F < SAFEOP:
                self._unrecoverable.add(i)
                self.view.fault(
                    f"slave {i} ({self.infos[i].name}) is in {state_name(states[i])}: "
                    "bringing it back needs a reconfiguration, which would stop the bus "
                    "for too long; it stays lost until the driver is opened again",
                    hold=False,
                )
        self._update_lost(states, lost)

    def _recovered(self, i: int) -> None:
        self.recovered += 1
        self._unrecoverable.discard(i)
        self._reported.discard(i)
        log.warning("ethercat %s: slave %d (%s) is back in OP", self.name, i, self.infos[i].name)

    # ------------------------------------------------------------ application API

    def tare(self, device: str) -> None:
        """Zero a force/torque sensor, named by its robot device (e.g. ``"wrist_ft"``) or its
        slave: its control output is set for a few cycles of the loop (the sensor tares on
        the edge), so the zeroed wrench shows a few ticks later."""
        for _, sensor in self.sensors:
            if isinstance(sensor, ForceTorqueDevice) and device.lower() in (
                sensor.record.name.lower(),
                sensor.slave.lower(),
            ):
                with self._lock:
                    try:
                        sensor.tare()
                    except VariableTypeError as exc:
                        raise EthercatError(str(exc)) from exc
                    if sensor not in self._taring:
                        self._taring.append(sensor)
                return
        names = [s.record.name for _, s in self.sensors if isinstance(s, ForceTorqueDevice)]
        raise EthercatError(f"no force/torque sensor {device!r} on this bus (there are: {', '.join(names) or 'none'})")

    def _position(self, slave: str | int) -> int:
        if isinstance(slave, int):
            if not 0 <= slave < len(self.infos):
                raise EthercatError(f"no slave at position {slave} (the bus has {len(self.infos)})")
            return slave
        for info in self.infos:
            if info.name.lower() == slave.lower():
                return info.position
        raise EthercatError(f"no slave named {slave!r} (slaves: {', '.join(i.name for i in self.infos)})")

    async def sdo_read(self, slave: str | int, index: int, subindex: int = 0, size: int = 0) -> bytes:
        """Upload an object over CoE; runs in the driver's thread, not on the tick."""
        position = self._position(slave)
        return await asyncio.get_running_loop().run_in_executor(
            self._executor, self.bus.sdo_read, position, index, subindex, size
        )

    async def sdo_write(self, slave: str | int, index: int, subindex: int, data: bytes) -> None:
        """Download an object over CoE; runs in the driver's thread, not on the tick."""
        position = self._position(slave)
        await asyncio.get_running_loop().run_in_executor(
            self._executor, self.bus.sdo_write, position, index, subindex, bytes(data)
        )

    # ------------------------------------------------------------ safety and shutdown

    def _bus_ready(self) -> bool:
        return self.bus.is_open

    def _send_holding(self) -> None:
        if self._outstanding:  # a frame of the tick's is still out: take it first
            self.bus.receive(1000)
            self._outstanding = False
        self._pack_outputs_holding()
        self.bus.send()
        self._outstanding = True

    def _cycle_holding(self) -> None:
        self._bringup_cycle(min(self.options.bringup_receive_timeout_us, 10_000))

    async def close(self) -> None:
        if self._executor is None:
            return  # never opened
        self._stop_keepalive(raise_error=False)
        self._remember_enabled()
        await asyncio.get_running_loop().run_in_executor(self._executor, self._shutdown)
        self._executor.shutdown(wait=False)

    def _shutdown(self, budget_s: float = 1.0) -> None:
        """Quick stop every drive and wait for it (the ramp), then disable it, within
        ``budget_s``; then every slave to INIT."""
        try:
            if self.bus.is_open and self.drives is not None and self.image is not None:
                self._stop_drives(budget_s, self.view.clock.period_ns * 1e-9)
        except Exception as exc:
            log.warning("ethercat %s: stopping the drives failed: %s", self.name, exc)
        finally:
            self.bus.close()

    def health(self) -> dict[str, Any]:
        if self._executor is None:
            return {}  # never opened
        n = min(self.cycles, RING)
        out: dict[str, Any] = {
            "interface": self.options.interface,
            "slaves": len(self.infos),
            "cycles": self.cycles,
            "wkc_errors": self.wkc_errors,
            "frames_lost": self.frames_lost,
            "expected_wkc": self._expected,
            "exchange": self.options.exchange,
        }
        if self.sm_watchdogs:
            out["sm_watchdog_ms"] = sorted(set(self.sm_watchdogs.values()))
        if self.image is not None:
            out["process_data_bytes"] = len(self.image.outputs) + len(self.image.inputs)
        if n:
            key = "rtt_us" if self.options.exchange == "immediate" else "receive_wait_us"
            step = max(1, n // HEALTH_SAMPLES)
            rtt, cpu = self._rtt_ns[:n:step], self._cpu_ns[:n:step]
            out[key] = _p50_p99_us(rtt)
            out["cpu_us"] = _p50_p99_us(cpu[cpu > 0]) if (cpu > 0).any() else {}
        if self.dc_lock is not None and self.dc_lock.count:
            out["dc_lock_error_us"] = _p50_p99_us(np.abs(self.dc_lock.recent_errors_ns()))
        if self._keepalive_cycles:
            out["keepalive_cycles"] = self._keepalive_cycles
        out["al_checks"] = self.al_checks
        if self.al_checks_unanswered:
            out["al_checks_unanswered"] = self.al_checks_unanswered
        if self.states_unanswered:
            out["states_unanswered"] = self.states_unanswered
        out.update(self._drives_health())
        if self.emergencies:
            out["emergencies"] = self.emergencies
        if self.lost or self.diagnoses:
            out["lost"] = [self.infos[i].name for i in sorted(self.lost)]
            out["diagnoses"] = self.diagnoses
            out["recovered"] = self.recovered
        return out


def _p50_p99_us(samples_ns: np.ndarray) -> dict[str, float]:
    p50, p99 = np.percentile(samples_ns, (50, 99)) / 1e3
    return {"p50": round(float(p50), 1), "p99": round(float(p99), 1)}
