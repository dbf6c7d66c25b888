"""The bus's state requests against a scripted master (no root, no pysoem)."""

from __future__ import annotations

import os
import time

import pytest

from aiohal.drivers.ethercat.bus import BOOT, INIT, OP, PREOP, SAFEOP, STATE_ERROR, BringUpError, Bus, reach_safeop


@pytest.fixture(autouse=True)
def lock_dir(tmp_path, monkeypatch):
    """Interface locks of these scripted buses in a directory of the test's own."""
    from aiohal.drivers.ethercat import bus

    monkeypatch.setattr(bus, "LOCK_DIR", tmp_path)
    return tmp_path


class Slave:
    def __init__(self, lose_requests: int = 0, state: int = PREOP) -> None:
        self.state = state  # as read by read_state; set to the requested state before write_state
        self.actual = state
        self.lose_requests = lose_requests  # requests lost on the wire, as in a stall
        self.requests = 0

    def write_state(self) -> None:
        self.requests += 1
        if self.requests > self.lose_requests and self.actual == PREOP:
            self.actual = self.state


class ScriptedMaster:
    """config_map has just asked every slave for SAFEOP once (each slave's first request)."""

    def __init__(self, slaves: list[Slave]) -> None:
        self.slaves = slaves
        self.checks = 0
        for slave in slaves:
            slave.state = SAFEOP
            slave.write_state()

    def state_check(self, state: int, timeout_us: int) -> int:
        """As SOEM's: one broadcast read ORs every slave's AL status; the error bit is masked."""
        self.checks += 1
        assert timeout_us >= 1000  # SOEM sleeps 1 ms between its reads: the wait never spins
        seen = 0
        for slave in self.slaves:
            seen |= slave.actual
        return seen & 0x0F

    def read_state(self) -> int:
        for slave in self.slaves:
            slave.state = slave.actual
        return min(s.actual for s in self.slaves)


def test_a_slave_whose_request_was_lost_is_asked_again():
    slaves = [Slave(), Slave(lose_requests=2), Slave()]
    master = ScriptedMaster(slaves)
    assert reach_safeop(master, timeout_s=5.0, poll_us=0)
    assert [s.actual for s in slaves] == [SAFEOP] * 3
    assert [s.requests for s in slaves] == [1, 3, 1]  # only the one left behind, twice more
    assert master.checks == 3


def test_a_slave_in_error_ends_the_wait_at_once_though_the_broadcast_reads_safeop():
    refused = Slave(state=SAFEOP | STATE_ERROR)  # e.g. its SyncManager settings refused
    master = ScriptedMaster([Slave(), refused])
    assert master.state_check(SAFEOP, 1000) == SAFEOP  # SOEM's check alone would call it done
    t0 = time.monotonic()
    assert not reach_safeop(master, timeout_s=5.0)
    assert time.monotonic() - t0 < 1.0
    assert refused.requests == 1  # config_map's own request only
    assert refused.state == SAFEOP | STATE_ERROR  # read back, for the error message


def test_slaves_in_init_boot_or_silent_are_not_asked_and_the_wait_ends_at_its_timeout():
    slaves = [Slave(state=INIT), Slave(state=BOOT), Slave(state=0), Slave()]
    master = ScriptedMaster(slaves)
    assert not reach_safeop(master, timeout_s=0.05)
    assert [s.requests for s in slaves] == [1, 1, 1, 1]  # an INIT or BOOT -> SAFEOP request is invalid
    assert [s.state for s in slaves] == [INIT, BOOT, 0, SAFEOP]


class OpMaster:
    """A master whose bus is in SAFEOP; the first ``lose`` OP requests are lost on the wire."""

    def __init__(self, slaves: int, lose: int, error_at: int | None = None) -> None:
        self.slaves = [Slave(state=SAFEOP) for _ in range(slaves)]
        self.state = SAFEOP
        self.lose = lose
        self.error_at = error_at  # after this many requests, slave 0 raises an AL error
        self.written: list[int] = []

    def write_state(self) -> None:
        self.written.append(self.state)
        if self.error_at is not None and len(self.written) >= self.error_at:
            self.slaves[0].actual = SAFEOP | STATE_ERROR
        if len(self.written) > self.lose and self.state == OP:
            for slave in self.slaves:
                if slave.actual == SAFEOP:
                    slave.actual = OP

    def state_check(self, state: int, timeout_us: int) -> int:
        seen = 0
        for slave in self.slaves:
            seen |= slave.actual
        self.state = seen  # as SOEM: the check leaves what it read (the error bit too) in slave 0's state
        return seen & 0x0F

    def read_state(self) -> int:
        for slave in self.slaves:
            slave.state = slave.actual
        return min(s.actual for s in self.slaves)


class FakeClock:
    """``time`` for the bus module: sleeping advances it, nothing waits."""

    def __init__(self) -> None:
        self.now = 0.0

    def monotonic(self) -> float:
        self.now += 1e-6
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


@pytest.fixture
def clock(monkeypatch):
    from aiohal.drivers.ethercat import bus

    fake = FakeClock()
    monkeypatch.setattr(bus, "time", fake)
    return fake


def _bus(master):
    from types import SimpleNamespace

    errors = SimpleNamespace(MailboxError=OSError, PacketError=OSError, WkcError=OSError,
                             al_status_code_to_string=lambda code: "no error")
    bus = Bus(errors, "scripted")
    bus.master, bus.slaves = master, master.slaves
    for slave in master.slaves:
        slave.name, slave.al_status = "AIOHAL-Drive", 0
    return bus


def test_the_op_request_is_sent_again_until_the_bus_is_in_op(clock):
    master = OpMaster(3, lose=2)
    cycles = []
    _bus(master).request_op(lambda: cycles.append(1), timeout_s=5.0, period_s=0.001, again_s=0.1)
    assert master.written == [OP] * 3  # never the acknowledge bit a state check read back
    assert [s.actual for s in master.slaves] == [OP] * 3
    assert 0.2 <= clock.now < 0.25 and len(cycles) > 200  # again every 0.1 s, the process data cycling all along


def test_op_not_reached_names_the_slaves_left_behind(clock):
    master = OpMaster(2, lose=10**6)
    with pytest.raises(BringUpError, match=r"did not reach OP within 0.5 s: slave 0 \(AIOHAL-Drive\) in SAFEOP"):
        _bus(master).request_op(lambda: None, timeout_s=0.5, period_s=0.001, again_s=0.1)
    assert master.written == [OP] * 5


def test_a_slave_in_error_ends_the_op_wait_at_once(clock):
    master = OpMaster(2, lose=10**6, error_at=2)
    with pytest.raises(BringUpError, match=r"did not reach OP: slave 0 \(AIOHAL-Drive\) in SAFEOP"):
        _bus(master).request_op(lambda: None, timeout_s=5.0, period_s=0.001, again_s=0.1)
    assert master.written == [OP] * 2 and clock.now < 0.25


class MailboxSlave:
    """``sdo_write`` loses its first ``lose`` frames, then aborts or stores."""

    name = "AIOHAL-Drive"

    def __init__(self, lose: int, abort: bool = False) -> None:
        self.lose, self.abort, self.calls, self.od = lose, abort, 0, {}

    def sdo_write(self, index: int, subindex: int, data: bytes, release_gil: bool = False) -> None:
        self.calls += 1
        if self.calls <= self.lose:
            raise OSError("no frame back")  # the scripted pysoem's WkcError
        if self.abort:
            raise LookupError("abort 0x06040041")  # stands for pysoem.SdoError: never retried
        self.od[index, subindex] = data


def test_a_mapping_write_whose_frame_was_lost_is_written_again_but_an_abort_is_not(clock):
    bus = _bus(OpMaster(1, lose=0))
    slave = MailboxSlave(lose=2)
    bus._sdo_write_again_if_lost(slave, 0x1601, 1, b"\x10\x00\x40\x60")
    assert slave.calls == 3 and slave.od == {(0x1601, 1): b"\x10\x00\x40\x60"}
    with pytest.raises(OSError):
        bus._sdo_write_again_if_lost(MailboxSlave(lose=3), 0x1601, 1, b"\0")  # three attempts, then the loss
    refusing = MailboxSlave(lose=0, abort=True)
    with pytest.raises(LookupError):
        bus._sdo_write_again_if_lost(refusing, 0x1601, 0, b"\0")
    assert refusing.calls == 1


class ScanMaster:
    """A pysoem Master whose first ``zero_scans`` bus scans read slave 1's identity as zero (its
    product code alone on the first scan), as SOEM does when an EEPROM read does not finish in time."""

    def __init__(self, zero_scans: int) -> None:
        self.zero_scans = zero_scans
        self.scans = 0
        self.slaves: list = []

    def open(self, ifname: str) -> None:
        pass

    def state_check(self, state: int, timeout_us: int) -> int:
        return PREOP  # nobody runs the bus: the broadcast read of the AL status finds PREOP

    def config_init(self, release_gil: bool = False) -> int:
        self.scans += 1
        unread = self.scans <= self.zero_scans
        self.slaves = [
            type("Slave", (), {"name": "drive", "man": 0xAB, "id": 0x402})(),
            type("Slave", (), {"name": "" if unread else "drive",
                               "man": 0 if unread and self.scans > 1 else 0xAB, "id": 0 if unread else 0x402})(),
        ]
        return len(self.slaves)


class ScanPysoem:
    MailboxError = PacketError = WkcError = type("LostFrame", (Exception,), {})

    def __init__(self, zero_scans: int) -> None:
        self.master = ScanMaster(zero_scans)

    def Master(self) -> ScanMaster:
        return self.master


@pytest.mark.parametrize("zero_scans", [0, 1, 2])
def test_a_zero_identity_is_read_again_by_scanning_the_bus_again(zero_scans):
    from aiohal.drivers.ethercat.bus import check_identity

    pysoem = ScanPysoem(zero_scans)
    bus = Bus(pysoem, "lo")
    assert bus.open() == 2
    assert pysoem.master.scans == zero_scans + 1
    assert [(s.man, s.id) for s in bus.slaves] == [(0xAB, 0x402)] * 2
    check_identity(1, bus.slaves[1].name, "drive2", bus.slaves[1].man, bus.slaves[1].id, 0xAB, 0x402)


def test_an_identity_still_zero_after_three_scans_fails_with_the_reason():
    from aiohal.drivers.ethercat.bus import IDENTITY_READS, check_identity

    pysoem = ScanPysoem(zero_scans=10)
    bus = Bus(pysoem, "lo")
    assert bus.open() == 2
    assert pysoem.master.scans == IDENTITY_READS == 3
    with pytest.raises(BringUpError) as err:
        check_identity(1, "?", "drive2", bus.slaves[1].man, bus.slaves[1].id, 0xAB, 0x402)
    assert "vendor id 0x00000000" in str(err.value) and "read as zero in 3 scans" in str(err.value)
    with pytest.raises(BringUpError) as wrong:  # a wrong device says nothing of scans
        check_identity(1, "other", "drive2", 0xAB, 0x999, 0xAB, 0x402)
    assert "scans" not in str(wrong.value)


# ---------------------------------------------------------------- slave-supplied bytes

from hypothesis import given
from hypothesis import strategies as st

from aiohal.drivers.ethercat.bus import (
    SlaveDataError,
    TransientBringUpError,
    mapping_entry,
    pdo_index,
    sdo_count,
)


@given(st.binary(max_size=8))
def test_an_entry_count_is_one_byte_of_at_most_254_or_a_named_error(data):
    try:
        count = sdo_count("slave 3 (X)", 0x1C12, data)
    except SlaveDataError as exc:
        assert str(exc).startswith("slave 3 (X): 0x1C12:00")
        assert len(data) == 0 or data[0] > 254
    else:
        assert count == data[0] <= 254


@given(st.sampled_from([0x1C12, 0x1C13]), st.integers(1, 254), st.binary(max_size=6))
def test_a_pdo_index_is_two_bytes_in_its_direction_s_range_or_a_named_error(index, sub, data):
    try:
        pdo = pdo_index("slave 0 (D)", index, sub, data)
    except SlaveDataError as exc:
        assert f"slave 0 (D): 0x{index:04X}:{sub:02X}" in str(exc)
    else:
        assert len(data) >= 2 and pdo == int.from_bytes(data[:2], "little")
        assert (0x1600 <= pdo <= 0x17FF) if index == 0x1C12 else (0x1A00 <= pdo <= 0x1BFF)


@given(st.integers(0x1600, 0x1BFF), st.integers(1, 254), st.binary(max_size=8))
def test_a_mapping_entry_is_four_bytes_of_1_to_64_bits_or_a_named_error(index, sub, data):
    try:
        entry = mapping_entry("slave 1 (D)", index, sub, data)
    except SlaveDataError as exc:
        assert f"slave 1 (D): 0x{index:04X}:{sub:02X}" in str(exc)
    else:
        assert len(data) >= 4 and entry == int.from_bytes(data[:4], "little") and 1 <= entry & 0xFF <= 64


class SdoSlave:
    """A CoE slave answering SDO reads from a table (bytes, or an exception to raise)."""

    name, man, id = "AIOHAL-Drive", 0x000A1A1A, 0x402

    def __init__(self, od: dict) -> None:
        self.od = od

    def sdo_read(self, index, subindex, size=0, release_gil=False):
        value = self.od.get((index, subindex), LookupError(0x06020000))
        if isinstance(value, Exception):
            raise value
        return value


class SdoPysoem:
    MailboxError = PacketError = WkcError = type("LostFrame", (Exception,), {})

    class SdoError(Exception):
        def __init__(self, abort_code: int) -> None:
            self.abort_code, self.desc = abort_code, "object does not exist"


GOOD_OD = {(0x1000, 0): (0x00020192).to_bytes(4, "little"),
           (0x1C12, 0): b"\x01", (0x1C12, 1): (0x1600).to_bytes(2, "little"),
           (0x1C13, 0): b"\x01", (0x1C13, 1): (0x1A00).to_bytes(2, "little"),
           (0x1600, 0): b"\x01", (0x1600, 1): (0x60400010).to_bytes(4, "little"),
           (0x1A00, 0): b"\x01", (0x1A00, 1): (0x60410010).to_bytes(4, "little")}


def _coe_bus(od: dict) -> Bus:
    bus = Bus(SdoPysoem, "scripted")
    bus.slaves = [SdoSlave(od)]
    bus.sii = lambda position: None
    return bus


@pytest.mark.parametrize(("key", "value", "message"), [
    ((0x1C12, 0), b"", "0x1C12:00 (number of entries) came back empty"),
    ((0x1C12, 1), b"\x00", "0x1C12:01 came back with 1 byte(s), a PDO index needs 2"),
    ((0x1C13, 1), (0x1600).to_bytes(2, "little"), "0x1C13:01 = 0x1600, not a PDO of this direction"),
    ((0x1600, 1), b"\x10\x00\x40", "0x1600:01 came back with 3 byte(s), a mapping entry needs 4"),
    ((0x1A00, 0), b"\xff", "0x1A00:00 = 255 entries, at most 254"),
    ((0x1A00, 1), (0x60410000).to_bytes(4, "little"), "a bit length of 0 (1..64)"),
])
def test_short_or_out_of_range_replies_fail_the_layout_naming_the_slave_and_object(monkeypatch, key, value, message):
    from aiohal.drivers.ethercat import sii as sii_layout

    monkeypatch.setattr(sii_layout, "has_coe", lambda sii: True)
    bus = _coe_bus({**GOOD_OD, key: value})
    with pytest.raises(SlaveDataError) as err:
        bus.read_layout(0)
    assert str(err.value).startswith("slave 0 (AIOHAL-Drive): ") and message in str(err.value)
    assert not isinstance(err.value, TransientBringUpError)  # the same bytes would come again


def test_a_coe_slave_without_a_pdo_assignment_is_read_from_its_sii(monkeypatch):
    from aiohal.drivers.ethercat import sii as sii_layout

    od = {k: v for k, v in GOOD_OD.items() if k[0] not in (0x1C12, 0x1C13)}
    od[0x1C12, 0] = SdoPysoem.SdoError(0x06020000)
    monkeypatch.setattr(sii_layout, "has_coe", lambda sii: True)
    monkeypatch.setattr(sii_layout, "read_pdos", lambda sii: ({0x1600: [(0x6040, 0, 16, "Controlword")]},
                                                              {0x1A00: [(0x6041, 0, 16, "Statusword")]}))
    bus = _coe_bus(od)
    layout = bus.read_layout(0)
    assert (layout.output_bits, layout.input_bits) == (16, 16)
    od[0x1C12, 0] = SdoPysoem.SdoError(0x06090011)  # another abort is not a missing object: it says so
    with pytest.raises(Exception, match="abort 0x06090011"):
        bus.read_layout(0)


def test_a_held_interface_is_refused_naming_the_holder(lock_dir):
    first = Bus(ScanPysoem(0), "ah1m")
    first._hold_interface()
    try:
        with pytest.raises(BringUpError, match=r"'ah1m' is held by another aiohal process \(pid \d+"):
            Bus(ScanPysoem(0), "ah1m")._hold_interface()
        Bus(ScanPysoem(0), "ah2m")._hold_interface()  # another interface: its own lock
    finally:
        first._release_interface()
    second = Bus(ScanPysoem(0), "ah1m")
    second._hold_interface()  # released with the bus
    second._release_interface()


def test_the_interface_lock_file_is_removed_with_the_bus_and_a_removed_one_is_not_trusted(lock_dir, monkeypatch):
    from aiohal.drivers.ethercat import bus as bus_module

    first = Bus(ScanPysoem(0), "ah3m")
    first._hold_interface()
    path = lock_dir / "aiohal-ethercat-ah3m.lock"
    assert path.read_text().strip() == str(os.getpid())
    first._release_interface()
    assert not path.exists()  # nothing left under the lock directory
    # a lock file that another program removes between open and lock each time is refused,
    # after a bounded number of tries, rather than trusted
    real_flock = bus_module.fcntl.flock
    tries = []

    def flock_then_remove(fd, op):
        real_flock(fd, op)
        tries.append(fd)
        path.unlink()

    monkeypatch.setattr(bus_module.fcntl, "flock", flock_then_remove)
    with pytest.raises(BringUpError, match="keeps being removed"):
        Bus(ScanPysoem(0), "ah3m")._hold_interface()
    assert len(tries) == 5
