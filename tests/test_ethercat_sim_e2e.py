"""Real SOEM (pysoem 1.1.13) against the simulated segment over a veth pair (needs root).

Each fixture starts ``python -m aiohal.drivers.ethercat.sim`` inside ``unshare --net`` and
moves one end of a fresh veth pair into that namespace; the master opens only the other end.
Receive timeouts are 50 ms (the reference notes measured no miss at 50 ms with three CPU hogs
on two cores, and a few at 2 ms): the CI machine's two cores are shared by the master, the
simulator and whatever else the test run does.
"""

from __future__ import annotations

import gc
import os
import shutil
import signal
import struct
import subprocess
import time

import pytest
from conftest import require_module, require_root

pytestmark = pytest.mark.root

RX_TIMEOUT_US = 50_000  # >= 20 ms; 50 ms rides out the scheduling stalls of a loaded 2-core VM
LINE = "dio,drive*2,imu,ft"  # bus order: 0 dio, 1-2 drives, 3 imu, 4 ft
# SM watchdog of the e2e segments: longer than the default 100 ms (exact semantics are unit
# tested) so that a stall of the shared test machine does not disable the drives mid-test
WATCHDOG_MS = 250
# the 25-slave run's: a CI host stalled this process past 250 ms in each of three attempts
# (frames lost for 50-180 ms in a row); the scale test is about working counters, not watchdogs
SCALE_WATCHDOG_MS = 1000


def _environment():
    require_root("veth pairs and network namespaces for the simulated EtherCAT segment")
    missing = [tool for tool in ("ip", "unshare") if shutil.which(tool) is None]
    if missing:
        reason = f"missing {', '.join(missing)} (iproute2 / util-linux)"
        if os.environ.get("CI") == "true":
            pytest.fail(reason)
        pytest.skip(reason)
    return require_module("pysoem")


@pytest.fixture(scope="module")
def pysoem():
    mod = _environment()
    saved = mod.settings.timeouts.ret
    mod.settings.timeouts.ret = RX_TIMEOUT_US  # every non-cyclic frame (bring-up, state reads) rides out a stall too
    yield mod
    mod.settings.timeouts.ret = saved


def _start(slaves, **kw):
    from aiohal.drivers.ethercat.sim.fixture import SimulatedSegment

    return SimulatedSegment(slaves, **kw)


@pytest.fixture(scope="module")
def line(pysoem):
    with _start(LINE, watchdog_ms=WATCHDOG_MS) as sim:
        yield sim
    assert not _link_exists(sim.ifname)


def _link_exists(name: str) -> bool:
    out = subprocess.run(["ip", "-br", "link"], capture_output=True, text=True, check=True).stdout
    return any(row.split()[0].split("@")[0] == name for row in out.splitlines() if row.strip())


class Master:
    """pysoem bring-up and cycling, as a driver would do it."""

    def __init__(self, pysoem, sim, overlap=False):
        self.p = pysoem
        self.sim = sim
        sim.control({"cmd": "clear"})
        sim.control({"cmd": "power_cycle"})
        self.m = pysoem.Master()
        self.m.open(sim.ifname)
        self.overlap = overlap
        self.bad: list[tuple[int, int, float]] = []  # (cycle, wkc, round-trip ms) of bad cycles
        self.cycles = 0

    def close(self):
        self.m.close()

    def init(self):
        """config_init, retried like a driver would: a reply held up by a busy machine beyond
        SOEM's datagram timeout makes config_init return -1/-2 (no frame / another frame)."""
        for _ in range(3):
            n = self.m.config_init()
            if n > 0:
                return n
        return n

    def to_safeop(self):
        """config_map asks for SAFEOP once; the driver's wait (which asks again a slave left
        behind by a frame lost in a stall: seen in CI, state 0x06) with a CI-sized timeout."""
        from aiohal.drivers.ethercat.bus import reach_safeop

        size = self.m.config_overlap_map() if self.overlap else self.m.config_map()
        assert reach_safeop(self.m, 5.0), [hex(s.state) for s in self.m.slaves]
        return size

    def to_op(self):
        """SAFEOP → OP as the driver does it (the request repeated until there), for at most 5 s."""
        from aiohal.drivers.ethercat.bus import reach_op

        if not reach_op(self.m, lambda: self.cycle(1), 5.0, 0.0):
            raise AssertionError([hex(s.al_status) for s in self.m.slaves])

    def acknowledge_and_op(self):
        """Acknowledge an AL error (e.g. an SM watchdog that tripped) and go back to OP."""
        self.m.state = self.p.SAFEOP_STATE | self.p.STATE_ACK
        self.m.write_state()
        self.cycle(2)
        self.to_op()

    def up(self):
        assert self.init() > 0
        size = self.to_safeop()
        self.m.config_dc()
        self.to_op()
        return size

    @property
    def wrong(self):
        """Cycles whose frame came back with a wrong working counter: never acceptable."""
        return [b for b in self.bad if b[1] != -1]

    @property
    def lost(self):
        """Cycles whose frame did not come back within the timeout (a stall of the machine)."""
        return [b for b in self.bad if b[1] == -1]

    def good_cycles(self, n, max_cycles, period=0.001, in_a_row=True):
        """Cycle until n cycles (in a row, or in all) had the expected working counter, bounded
        by max_cycles; how many. In a row: the reference notes' tolerant form of "n cycles
        without error", which a stall of the shared 2-core machine cannot fail. In all: for
        runs longer than the machine goes without a stall, the caller holding each lost frame
        against the simulator's late replies. Wrong counters are never tolerated."""
        good = 0
        for _ in range(max_cycles):
            before = len(self.bad)
            self.cycle(1, period)
            if len(self.bad) == before:
                good += 1
            elif in_a_row:
                good = 0
            if good >= n:
                break
        return good

    def cycle(self, n=1, period=0.001, on_cycle=None):
        """n process-data cycles paced at ``period`` (deadline based); returns the last WKC.
        The collector is off meanwhile, as in a real-time loop (a long gen-2 pause of the big
        test process would otherwise starve the slaves' SM watchdogs)."""
        gc_was_on = gc.isenabled()
        gc.disable()
        try:
            return self._cycle(n, period, on_cycle)
        finally:
            if gc_was_on:
                gc.enable()

    def _cycle(self, n, period, on_cycle):
        wkc = 0
        deadline = time.monotonic()
        for i in range(n):
            if on_cycle is not None:
                on_cycle(i)
            t0 = time.perf_counter()
            if self.overlap:
                self.m.send_overlap_processdata()
            else:
                self.m.send_processdata()
            wkc = self.m.receive_processdata(RX_TIMEOUT_US)
            self.cycles += 1
            if wkc != self.m.expected_wkc:
                self.bad.append((self.cycles, wkc, round((time.perf_counter() - t0) * 1e3, 2)))
            deadline += period
            left = deadline - time.monotonic()
            if left > 0:
                time.sleep(left)
            else:
                deadline = time.monotonic()
        return wkc


@pytest.fixture()
def master(pysoem, line):
    m = Master(pysoem, line)
    yield m
    m.close()


# ====================================================================== bring-up


def _read_register(pysoem, slave, address, size, attempts=3):
    """FPRD with the fixture's receive timeout, retried: a read is idempotent, and pysoem's
    default 2 ms timeout turns a stall of the shared machine into a WkcError (seen in CI)."""
    for _ in range(attempts - 1):
        try:
            return slave._fprd(address, size, timeout_us=RX_TIMEOUT_US)
        except pysoem.WkcError:
            pass
    return slave._fprd(address, size, timeout_us=RX_TIMEOUT_US)


def test_discovery_identity_mapping_dc_and_op(master, pysoem):
    m = master.m
    assert master.init() == 5
    names = [s.name for s in m.slaves]
    assert names == ["AIOHAL-DIO8", "AIOHAL-Drive", "AIOHAL-Drive", "AIOHAL-IMU", "AIOHAL-FT"]
    assert {s.man for s in m.slaves} == {0x000A1A1A}
    assert [s.id for s in m.slaves] == [0x808, 0x402, 0x402, 0x1300, 0x1600]
    size = master.to_safeop()
    # outputs: dio 1 + drives 2 x 13 + ft 2; inputs: dio 1 + drives 2 x 15 + imu 42 + ft 26
    assert size == 29 + 99
    assert [len(s.output) for s in m.slaves] == [1, 13, 13, 0, 2]
    assert [len(s.input) for s in m.slaves] == [1, 15, 15, 42, 26]
    assert m.expected_wkc == 2 * 4 + 5
    assert m.config_dc()
    t0 = m.dc_time
    master.to_op()
    master.cycle(20)
    assert m.dc_time > t0
    m.slaves[1].dc_sync(True, 1_000_000)  # SYNC0 registers are stored (pulses are not modelled)
    assert _read_register(pysoem, m.slaves[1], 0x0981, 1) == b"\x03"
    assert _read_register(pysoem, m.slaves[1], 0x09A0, 4) == struct.pack("<I", 1_000_000)
    start = struct.unpack("<Q", _read_register(pysoem, m.slaves[1], 0x0990, 8))[0]
    assert start > m.dc_time  # the next pulse lies ahead of the master's DC time
    assert not master.wrong and len(master.lost) <= 2, master.bad
    assert m.read_state() == pysoem.OP_STATE
    # process data both ways: the terminal loops back, the IMU feels gravity
    m.slaves[0].output = b"\xa5"
    master.cycle(3)
    assert m.slaves[0].input == b"\xa5"
    q = struct.unpack("<4f3f3fH", m.slaves[3].input)
    assert q[0] == 1.0 and abs(q[9] - 9.80665) < 1e-5 and q[10] == 1
    master.sim.control({"cmd": "device", "slave": 4, "wrench": [1, 2, 3, 4, 5, 6]})
    master.cycle(2)
    assert struct.unpack("<6fH", m.slaves[4].input) == (1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 1)


def test_overlap_map_and_1000_cycles_without_wkc_errors(pysoem, line):
    master = Master(pysoem, line, overlap=True)
    try:
        assert master.init() == 5
        size = master.to_safeop()
        # every slave's inputs overlay its outputs: per slave max(out, in) = 1, 15, 15, 42, 26;
        # SOEM returns Obytes + Ibytes, Obytes ending with the last slave's outputs (73 + 2)
        assert size == 75 + 99 and master.m.expected_wkc == 2 * 4 + 5
        master.m.config_dc()
        master.to_op()
        master.bad.clear()
        t0 = time.monotonic()
        assert master.good_cycles(1000, 3000) == 1000, master.bad
        assert not master.wrong, master.bad
        assert time.monotonic() - t0 < 15.0
    finally:
        master.close()


def test_bit_packed_terminals_share_a_byte(pysoem):
    with _start("dio4,dio4,drive", watchdog_ms=WATCHDOG_MS) as sim:
        master = Master(pysoem, sim)
        try:
            assert master.init() == 3
            assert master.to_safeop() == 1 + 13 + 1 + 15
            master.m.config_dc()
            master.to_op()
            m = master.m
            m.slaves[0].output = b"\x3a"  # low nibble: terminal 0, high nibble: terminal 1
            wkc = master.cycle(3)
            assert m.slaves[0].input == b"\x3a" and m.slaves[1].input == b"\x3a"
            st = sim.status()["slaves"]
            assert st[0]["device"]["outputs"] == 0xA and st[1]["device"]["outputs"] == 0x3
            # every ESC whose FMMU is hit counts; SOEM 1.4 under-counts terminals that do not
            # end a byte (docs/ethercat.md), so its expected_wkc is 3 lower here
            assert wkc == 3 + 3 + 3 and m.expected_wkc == wkc - 3
        finally:
            master.close()
    assert not _link_exists(sim.ifname) and not _link_exists(sim.peer)


# ====================================================================== CoE


def test_sdo_round_trips(master, pysoem):
    master.init()
    drive = master.m.slaves[1]
    assert drive.sdo_read(0x1000, 0) == struct.pack("<I", 0x00020192)
    assert drive.sdo_read(0x1008, 0) == b"AIOHAL-Drive"
    assert drive.sdo_read(0x100A, 0).startswith(b"aiohal-sim")
    drive.sdo_write(0x6072, 0, struct.pack("<H", 750))
    assert drive.sdo_read(0x6072, 0) == struct.pack("<H", 750)
    info = drive.sdo_read(0x2000, 0)  # segmented upload
    assert len(info) > 128 and info.startswith(b"aiohal simulated")
    blob = bytes((3 * i + 1) & 0xFF for i in range(256))
    drive.sdo_write(0x2001, 0, blob)  # segmented download
    assert drive.sdo_read(0x2001, 0) == blob
    assert drive.sdo_read(0x1C12, 0, ca=True) == b"\x01\x00\x00\x16"
    with pytest.raises(pysoem.SdoError) as exc:
        drive.sdo_read(0x5555, 0)
    assert exc.value.abort_code == 0x06020000
    with pytest.raises(pysoem.SdoError) as exc:
        drive.sdo_write(0x1000, 0, struct.pack("<I", 1))
    assert exc.value.abort_code == 0x06010002
    with pytest.raises(pysoem.SdoError) as exc:
        drive.sdo_write(0x6072, 0, struct.pack("<I", 1))
    assert exc.value.abort_code == 0x06070010


def test_remap_in_preop_through_a_config_hook(master, pysoem):
    """A driver may remap in PREOP (pysoem config_func); SM lengths follow the mapping."""
    master.init()
    drive = master.m.slaves[1]

    def remap(slave_pos):
        drive.sdo_write(0x1C12, 0, b"\x01\x00" + struct.pack("<H", 0x1601), ca=True)
        drive.sdo_write(0x1C13, 0, b"\x01\x00" + struct.pack("<H", 0x1A01), ca=True)

    drive.config_func = remap
    master.to_safeop()
    assert len(drive.output) == 6 and len(drive.input) == 6
    master.to_op()
    assert master.cycle(5) == master.m.expected_wkc


# ====================================================================== drive


def _drive_outputs(cw, pos=0, vel=0, torque=0, mode=8):
    return struct.pack("<HiihB", cw, pos, vel, torque, mode)


def _drive_inputs(slave):
    return struct.unpack("<HiihbH", slave.input)


# CiA 402 statusword & 0x6F after each controlword of the enable sequence
STATUS_AFTER = {0x06: 0x21, 0x07: 0x23, 0x0F: 0x27}


def _command_drives(master, drives, controlwords, position=0, max_cycles=200):
    """Each controlword in turn, cycled until every drive's statusword shows the state it leads
    to (bounded), as a master's state machine waits for it: a frame lost in a stall of the
    shared machine then delays the step instead of failing it."""
    for cw in controlwords:
        for d in drives:
            d.output = _drive_outputs(cw, position)
        for _ in range(max_cycles):
            master.cycle(1)
            words = [_drive_inputs(d)[0] for d in drives]
            if all(w & 0x6F == STATUS_AFTER[cw] for w in words):
                break
        else:
            raise AssertionError(f"controlword 0x{cw:02X}: statuswords {[hex(w) for w in words]}, bad {master.bad}")


def test_drive_enable_and_follow_csp(master, pysoem):
    master.up()
    drive = master.m.slaves[1]
    start = _drive_inputs(drive)[1]
    _command_drives(master, [drive], (0x06, 0x07, 0x0F), start)
    sw = _drive_inputs(drive)[0]
    assert sw & 0x6F == 0x27, hex(sw)

    velocities, lags = [], []

    def ramp(i):
        _sw, pos, vel, *_rest = _drive_inputs(drive)
        velocities.append(vel)
        lags.append(start + 50 * (i - 1) - pos)  # behind the target sent one cycle earlier
        drive.output = _drive_outputs(0x0F, start + 50 * i)

    master.cycle(400, on_cycle=ramp)
    target = start + 50 * 399
    # the last target held until the drive stands on it (bounded): a stall of this machine in
    # the ramp (seen with emulated stalls) leaves the simulated drive behind for a while
    for _ in range(500):
        sw, pos, _vel, _tq, mode, code = _drive_inputs(drive)
        if abs(target - pos) < 1_000:
            break
        master.cycle(1)
    assert mode == 8 and code == 0
    assert abs(target - pos) < 1_000, (target, pos)
    assert max(velocities) > 0
    assert sorted(abs(lag) for lag in lags)[len(lags) // 2] < 1_000, lags  # it followed the ramp
    assert not master.wrong, master.bad


def test_drive_fault_emergency_and_reset(master, pysoem):
    master.up()
    drive = master.m.slaves[2]
    seen = []
    drive.add_emergency_callback(seen.append)
    _command_drives(master, [drive], (0x06, 0x0F))
    master.sim.control({"cmd": "drive_fault", "slave": 2, "code": 0x2310})
    master.cycle(4)
    sw, *_rest, code = _drive_inputs(drive)
    assert sw & 0x4F == 0x08 and code == 0x2310
    assert drive.sdo_read(0x603F, 0) == struct.pack("<H", 0x2310)  # the mailbox brings the EMCY
    assert [e.error_code for e in seen] == [0x2310]
    drive.output = _drive_outputs(0x80)
    master.cycle(3)
    sw, *_rest, code = _drive_inputs(drive)
    assert sw & 0x4F == 0x40 and code == 0


# ====================================================================== losing slaves


def test_cable_break_seen_in_wkc_then_recovery(master, pysoem):
    master.up()
    m = master.m
    expected = m.expected_wkc
    master.sim.control({"cmd": "break", "slave": 2})  # drive 2, imu and ft vanish
    wkc = master.cycle(5)
    assert 0 < wkc < expected and wkc == 3 + 3  # dio and the first drive still answer
    for _ in range(40):  # keep the first slaves fed while the others starve (> watchdog)
        master.cycle(10)
    master.sim.control({"cmd": "repair"})
    assert master.cycle(2) == expected  # reachable again...
    m.read_state()
    # ...but the SM watchdogs of the slaves with outputs behind the break ran out
    assert [s.state for s in m.slaves] == [pysoem.OP_STATE, pysoem.OP_STATE,
                                           pysoem.SAFEOP_STATE | pysoem.STATE_ERROR, pysoem.OP_STATE,
                                           pysoem.SAFEOP_STATE | pysoem.STATE_ERROR]
    assert [s.al_status for s in m.slaves] == [0, 0, 0x001B, 0, 0x001B]
    for k in (2, 4):  # recovery as a driver does it: acknowledge, valid outputs, OP
        m.slaves[k].state = pysoem.SAFEOP_STATE | pysoem.STATE_ACK
        m.slaves[k].write_state()
    master.cycle(2)
    for k in (2, 4):
        m.slaves[k].state = pysoem.OP_STATE
        m.slaves[k].write_state()
    master.cycle(2)
    assert m.read_state() == pysoem.OP_STATE


def test_watchdog_when_the_master_stops(master, pysoem):
    master.up()
    drive = master.m.slaves[1]
    _command_drives(master, [drive], (0x06, 0x0F))
    # no process data for longer than the SM watchdog (250 ms): polled, bounded, since the
    # simulator does not count a stall of the host against the watchdog (1.3 s seen)
    deadline = time.monotonic() + 5.0
    time.sleep(0.3)
    while (st := master.sim.status()["slaves"])[1]["state"] == "OP" and time.monotonic() < deadline:
        time.sleep(0.05)
    assert st[1]["state"] == "SAFEOP" and st[1]["al_status_code"] == 0x001B
    assert st[1]["device"]["state"] == "switch_on_disabled"  # the drive disabled itself
    assert st[3]["state"] == "OP"  # no outputs, no watchdog
    master.m.read_state()
    assert master.m.slaves[1].al_status == 0x001B


def test_frame_faults_drop_delay_wrong_wkc(master, pysoem):
    master.up()
    m = master.m
    expected = m.expected_wkc
    master.sim.control({"cmd": "drop", "count": 3})
    wkcs = [master.cycle(1) for _ in range(6)]
    # the simulator's counter says exactly 3 were dropped (below); a stall may lose one more
    assert wkcs[:3] == [-1, -1, -1] and set(wkcs[3:]) <= {expected, -1} and expected in wkcs[3:]
    master.sim.control({"cmd": "delay", "ms": 5, "count": 5})
    t0 = time.monotonic()
    assert master.cycle(5, period=0) == expected
    assert time.monotonic() - t0 >= 0.025
    master.sim.control({"cmd": "wkc", "count": 2})
    wkcs = [w for w in (master.cycle(1) for _ in range(5)) if w != -1]  # -1: a frame lost in a stall
    # one short, then right again (how many were corrupted: the simulator's counter, below)
    assert wkcs[0] == expected - 1 and wkcs[-1] == expected and wkcs == sorted(wkcs), wkcs
    status = master.sim.status()
    assert status["counters"]["dropped"] == 3 and status["counters"]["wkc_corrupted"] == 2
    master.sim.control({"cmd": "al_error", "slave": 4, "code": 0x0020})
    assert m.read_state() == pysoem.SAFEOP_STATE
    assert m.slaves[4].al_status == 0x0020


def test_a_reply_held_up_by_a_stalled_simulator_is_counted_late(master, pysoem):
    """The simulator counts process-data replies that left long after their frame arrived
    (the kernel's stamp): how a test tells frames lost to a stall of this machine from a
    driver's fault."""
    master.up()
    m = master.m
    late = [f"late_{us}us" for us in (200, 1000, 2000, 10_000)]
    before = master.sim.status()["counters"]
    for _attempt in range(3):  # (a SIGCONT from elsewhere could end the stall early: try again)
        os.kill(master.sim.pid, signal.SIGSTOP)  # a stall of the simulator alone
        try:
            m.send_processdata()
            wkc = m.receive_processdata(20_000)
        finally:
            os.kill(master.sim.pid, signal.SIGCONT)
        if wkc == -1:  # nobody answered within 20 ms
            break
    assert wkc == -1
    # the late reply is stale now: SOEM drops it (its datagram index was released), and the
    # cycles after it come back again
    cycles_before = master.cycles
    assert master.good_cycles(20, 2000) == 20
    after = master.sim.status()["counters"]
    grown = {k: after[k] - before[k] for k in late}
    assert all(g >= 1 for g in grown.values()), grown  # the reply, > 20 ms late, counts at each threshold
    # not every reply: the cycles after it were answered within a few ms (bar a stall of 10 ms)
    assert grown["late_10000us"] <= 1 + (master.cycles - cycles_before) // 2, grown


# ====================================================================== scale


def test_25_slaves_at_1khz(pysoem):
    with _start("drive*21,imu,ft,dio,dio", watchdog_ms=SCALE_WATCHDOG_MS) as sim:
        master = Master(pysoem, sim)
        try:
            assert master.init() == 25
            assert master.to_safeop() == 21 * 28 + 42 + 28 + 2 + 2
            master.m.config_dc()
            master.to_op()
            drives = master.m.slaves[:21]
            _command_drives(master, drives, (0x06, 0x0F))
            attempts = 3
            for attempt in range(attempts):
                before = sim.status()["counters"]
                trips = before["watchdog_trips"]
                master.bad.clear()
                good = master.good_cycles(1000, 3000, in_a_row=False)
                status = sim.status()
                if status["counters"]["watchdog_trips"] == trips or attempt == attempts - 1:
                    break
                # this process stalled longer than the SM watchdog (1 s) while the simulator ran
                # (its own stalls it discounts): the slaves dropped to SAFEOP+error and the drives
                # disabled, as on a real segment, and a slave in SAFEOP still counts in the working
                # counter. Acknowledge, back to OP, enable, and run the 1000 cycles again (at most
                # three attempts: a fresh-clone run on a host stalling 10-55 % tripped it twice).
                master.acknowledge_and_op()
                _command_drives(master, drives, (0x06, 0x0F))
            assert good == 1000, (master.bad, status["counters"])
            assert not master.wrong, master.bad
            # every frame lost (none came back within 50 ms) is a reply the simulator sent more
            # than 50 ms late: it was not run (a stall of this machine); a few more for a stall
            # that caught the master between its last look at the socket and its timeout
            late = status["counters"]["late_50000us"] - before["late_50000us"]
            assert len(master.lost) <= late + 5, (master.lost, late)
            assert status["counters"]["watchdog_trips"] == trips, ("the watchdog tripped in every attempt", master.bad)
            states = [s["device"].get("state") for s in status["slaves"][:21]]
            assert states == ["operation_enabled"] * 21, (states, master.bad)
        finally:
            master.close()
    assert not _link_exists(sim.ifname)
