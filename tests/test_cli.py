"""``python -m aiohal`` as a user runs it: a subprocess, exit codes, stdout/stderr."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bad_configs import CASES, MANY, matches

ROOT = Path(__file__).resolve().parent.parent
TIMEOUT = 30  # seconds, for every subprocess


def run_cli(*args: str | Path, timeout: float = TIMEOUT, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "aiohal", *map(str, args)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
    )


def assert_no_traceback(proc: subprocess.CompletedProcess) -> None:
    assert "Traceback" not in proc.stdout, proc.stdout
    assert "Traceback" not in proc.stderr, proc.stderr


def issue_lines(stderr: str) -> list[str]:
    """The indented issue lines of a printed ConfigError."""
    return [line[2:] for line in stderr.splitlines() if line.startswith("  ")]


def write(tmp_path: Path, text: str, name: str = "robot.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# ---------------------------------------------------------------- check


def test_check_reports_every_error_with_its_path(tmp_path):
    path = write(tmp_path, MANY.toml)
    proc = run_cli("check", path)
    assert proc.returncode == 2
    assert_no_traceback(proc)
    assert proc.stdout == ""
    lines = proc.stderr.splitlines()
    assert lines[0] == f"{path}: invalid configuration ({len(MANY.expected)} error(s)):"
    printed = issue_lines(proc.stderr)
    assert len(printed) == len(MANY.expected)
    for expected in MANY.expected:
        assert any(matches(expected, line) for line in printed), (expected, printed)


@pytest.mark.parametrize(
    "case",
    [c for c in CASES if c.id in {
        "invalid-toml", "unknown-loop-key", "rate-wrong-type", "driver-unknown-joint",
        "unknown-driver-type", "unknown-driver-option", "homing-pose-out-of-range", "driver-as-table",
    }],
    ids=lambda c: c.id,
)
def test_check_malformed_config_exits_2(tmp_path, case):
    path = write(tmp_path, case.toml)
    proc = run_cli("check", path)
    assert proc.returncode == 2, proc
    assert_no_traceback(proc)
    assert proc.stderr.splitlines()[0] == f"{path}: invalid configuration ({len(case.expected)} error(s)):"
    printed = issue_lines(proc.stderr)
    assert len(printed) == len(case.expected)
    for expected, line in zip(case.expected, printed):
        assert matches(expected, line), (expected, line)


def test_check_good_configs_exit_0():
    proc = run_cli("check", "configs/mock_arm.toml", "configs/mock_humanoid.toml")
    assert proc.returncode == 0, proc.stderr
    assert_no_traceback(proc)
    out = proc.stdout.splitlines()
    assert len(out) == 2
    assert out[0].startswith("configs/mock_arm.toml: ok: robot mock_arm, 7 joints, drivers: arm (mock, 7 joints)")
    assert out[1].startswith("configs/mock_humanoid.toml: ok: robot mock_humanoid, 33 joints, drivers: legs (mock, 12 joints)")


def test_check_continues_after_a_bad_config(tmp_path):
    bad = write(tmp_path, MANY.toml)
    proc = run_cli("check", bad, "configs/mock_arm.toml")
    assert proc.returncode == 2
    assert "configs/mock_arm.toml: ok:" in proc.stdout
    assert f"{bad}: invalid configuration" in proc.stderr


def test_check_missing_file_exits_2(tmp_path):
    proc = run_cli("check", tmp_path / "absent.toml")
    assert proc.returncode == 2
    assert_no_traceback(proc)
    assert "cannot read the file" in proc.stderr


# ---------------------------------------------------------------- run


def test_run_with_bad_config_exits_2_before_starting(tmp_path):
    path = write(tmp_path, MANY.toml)
    report = tmp_path / "report.json"
    proc = run_cli(path, "--duration", "0.1", "--report-json", report)
    assert proc.returncode == 2
    assert_no_traceback(proc)
    assert f"{path}: invalid configuration ({len(MANY.expected)} error(s)):" in proc.stderr
    assert "starting robot" not in proc.stderr  # nothing was started, no logging configured
    assert proc.stdout == ""
    assert not report.exists()


def test_negative_rate_exits_2_naming_loop_rate_hz(tmp_path):
    report = tmp_path / "report.json"
    proc = run_cli("configs/mock_arm.toml", "--rate", "-5", "--duration", "0.1", "--report-json", report)
    assert proc.returncode == 2
    assert_no_traceback(proc)
    assert proc.stderr.splitlines()[0] == "configs/mock_arm.toml: invalid configuration (1 error(s)):"
    (line,) = issue_lines(proc.stderr)
    assert line.startswith("loop.rate_hz (command line): ")
    assert "greater than or equal to 0.1" in line
    assert not report.exists()


def test_schema_prints_valid_json():
    proc = run_cli("schema")
    assert proc.returncode == 0, proc.stderr
    assert_no_traceback(proc)
    schema = json.loads(proc.stdout, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    assert {"driver", "joints"} <= set(schema["properties"])
    assert "driver_mock_options" in schema["$defs"]


REPORT_KEYS = {
    "rate_hz_target", "rate_hz_achieved", "ticks", "missed_ticks", "drift_us",
    "lateness_us", "work_us", "cpu_percent", "controller",
}


def test_short_virtual_run_writes_a_report(tmp_path):
    report_path = tmp_path / "report.json"
    proc = run_cli("configs/mock_arm.toml", "--duration", "0.3", "--clock", "virtual", "--report-json", report_path)
    assert proc.returncode == 0, proc.stderr
    assert_no_traceback(proc)
    assert proc.stdout.startswith("aiohal run report: mock_arm (7 joints, clock virtual, overrun policy skip)")
    assert "ticks        300 in " in proc.stdout
    report = json.loads(report_path.read_text())
    assert REPORT_KEYS <= set(report)
    assert {"p50", "p99", "p999", "max"} <= set(report["lateness_us"])
    assert {"p50", "p99"} <= set(report["work_us"])
    assert isinstance(report["controller"], dict) and report["controller"]["type"] == "sine"
    assert report["ticks"] == 300
    assert report["missed_ticks"] == 0
    assert report["rate_hz_target"] == 1000.0
    assert report["rate_hz_achieved"] == pytest.approx(1000.0)
    assert report["faults"] == []
    assert not (tmp_path / "report.json.tmp").exists()


@pytest.mark.realtime
def test_short_real_clock_run_on_uvloop(tmp_path):
    pytest.importorskip("uvloop")
    report_path = tmp_path / "report.json"
    # the shipped config, but for the loop's stall watchdog: a stall of this whole shared VM
    # longer than its 500 ms (1.3 s seen in CI) would stop the run (the watchdog is tested elsewhere)
    config = tmp_path / "mock_arm.toml"
    config.write_text((ROOT / "configs" / "mock_arm.toml").read_text().replace("[loop]\n", "[loop]\nstall_timeout_ms = 5000\n", 1))
    assert "stall_timeout_ms = 5000" in config.read_text()
    proc = run_cli(config, "--duration", "0.5", "--loop", "uvloop", "--quiet", "--report-json", report_path)
    assert proc.returncode == 0, proc.stderr
    assert_no_traceback(proc)
    assert proc.stdout == ""  # --quiet
    report = json.loads(report_path.read_text())
    # every one of the 500 deadlines was served or counted as missed (a shared VM may stall)
    assert report["ticks"] + report["missed_ticks"] in (500, 501), report
    assert report["ticks"] > 0
    assert report["clock"] != "virtual"
    assert report["faults"] == []


def test_spin_guard_from_the_command_line(tmp_path):
    report_path = tmp_path / "report.json"
    proc = run_cli("configs/mock_arm.toml", "--duration", "0.2", "--spin-guard-us", "200", "--quiet",
                   "--report-json", report_path)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(report_path.read_text())
    assert report["ticks"] + report["missed_ticks"] in (200, 201)
    assert report["lateness_us"]["min"] >= 0  # spins to the deadline, never early

    proc = run_cli("configs/mock_arm.toml", "--duration", "0.2", "--spin-guard-us", "800")
    assert proc.returncode == 2
    assert "realtime.spin_guard_us (command line)" in proc.stderr
    assert_no_traceback(proc)
