"""The bus's state wait against a scripted master (no root, no pysoem)."""

from __future__ import annotations

from aiohal.drivers.ethercat.bus import PREOP, SAFEOP, STATE_ERROR, reach_state


class Slave:
    def __init__(self, lose_requests: int = 0, state: int = PREOP) -> None:
        self.state = state  # as read by read_state; set to the requested state before write_state
        self.actual = state
        self.lose_requests = lose_requests  # requests lost on the wire, as in a stall
        self.requests = 0

    def write_state(self) -> None:
        self.requests += 1
        if self.requests > self.lose_requests:
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
        self.checks += 1
        states = {s.actual for s in self.slaves}
        return states.pop() if len(states) == 1 else _or(states)

    def read_state(self) -> int:
        for slave in self.slaves:
            slave.state = slave.actual
        return min(s.actual for s in self.slaves)


def _or(states: set[int]) -> int:
    out = 0
    for state in states:
        out |= state
    return out


def test_a_slave_whose_request_was_lost_is_asked_again():
    slaves = [Slave(), Slave(lose_requests=2), Slave()]
    master = ScriptedMaster(slaves)
    assert reach_state(master, SAFEOP, timeout_s=5.0, poll_us=0)
    assert [s.actual for s in slaves] == [SAFEOP] * 3
    assert [s.requests for s in slaves] == [1, 3, 1]  # only the one left behind, twice more
    assert master.checks == 3


def test_a_slave_in_error_is_not_asked_again_and_the_wait_ends_at_its_timeout():
    refused = Slave(lose_requests=10**6, state=PREOP | STATE_ERROR)
    master = ScriptedMaster([Slave(), refused])
    assert not reach_state(master, SAFEOP, timeout_s=0.05, poll_us=0)
    assert refused.requests == 1  # config_map's own request only
    assert refused.state == PREOP | STATE_ERROR  # read back for the error message
