"""The suite's judge of the host: a bare reference beside a realtime test, and a failure of a
test marked ``host_reference`` turned into a skip only where the reference itself missed."""

from __future__ import annotations

import time
from types import SimpleNamespace

import conftest
from conftest import HOST_UNFIT, HostReference


def _report_after(host, outcome: str, when: str = "call"):
    """What conftest's pytest_runtest_makereport leaves of a report of ``outcome``."""
    report = SimpleNamespace(outcome=outcome, failed=outcome == "failed", longrepr="AssertionError")
    item = SimpleNamespace(host_reference=host, path="tests/test_x.py", location=("tests/test_x.py", 41, "test_x"))
    wrapper = conftest.pytest_runtest_makereport(item, SimpleNamespace(when=when))
    next(wrapper)
    try:
        wrapper.send(SimpleNamespace(get_result=lambda: report))
    except StopIteration:
        pass
    return report


def test_a_failure_beside_a_reference_that_missed_is_a_skip_saying_so():
    unfit = SimpleNamespace(unfit_reason=lambda: f"{HOST_UNFIT}: a bare sleep loop woke 18.0 ms late")
    report = _report_after(unfit, "failed")
    assert report.outcome == "skipped" and HOST_UNFIT in report.longrepr[-1]
    assert report.longrepr[:2] == ("tests/test_x.py", 41)  # where the summary names it


def test_a_failure_on_a_fit_host_and_a_pass_stay_what_they_are():
    fit = SimpleNamespace(unfit_reason=lambda: None)
    assert _report_after(fit, "failed").outcome == "failed"
    unfit = SimpleNamespace(unfit_reason=lambda: f"{HOST_UNFIT}: ...")
    assert _report_after(unfit, "passed").outcome == "passed"
    assert _report_after(unfit, "failed", when="setup").outcome == "failed"  # only the test's own call


def test_the_reference_measures_its_own_lateness():
    """A bare loop of 1 ms deadlines in a process of its own: its worst lateness is above zero
    (a wake is never early) and far below a second on any host that runs the suite at all."""
    host = HostReference(1000.0)
    time.sleep(0.2)
    assert host.unfit_reason() is None
    assert 0.0 < host.worst_ms < 1000.0
    strict = HostReference(0.0)
    time.sleep(0.05)
    assert HOST_UNFIT in strict.unfit_reason()
