"""``python -m aiohal`` as a user runs it: a subprocess, exit codes, stdout/stderr (the tables of
bad input through the same ``main`` in this process)."""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import select
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from bad_configs import CASES, MANY, matches

from aiohal.cli import main

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


def cli_in_process(*args: str | Path) -> subprocess.CompletedProcess:
    """``aiohal.cli.main`` in this process, its output captured: for the tables of bad input,
    whose subject is the message and the status, not the process around them (a subprocess
    test keeps each path through the process). Each saves an interpreter's start (1-2 s)."""
    argv = [str(arg) for arg in args]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.chdir(ROOT), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            status = main(argv)
        except SystemExit as exc:  # argparse's refusal
            status = exc.code if isinstance(exc.code, int) else 1
    return subprocess.CompletedProcess([sys.executable, "-m", "aiohal", *argv], status, out.getvalue(), err.getvalue())


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
    proc = cli_in_process("check", path)
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
        "udp-sim-bad-dynamics", "fri-sim-bad-servo-parameter",
    }],
    ids=lambda c: c.id,
)
def test_check_malformed_config_exits_2(tmp_path, case):
    path = write(tmp_path, case.toml)
    proc = cli_in_process("check", path)
    assert proc.returncode == 2, proc
    assert_no_traceback(proc)
    assert proc.stderr.splitlines()[0] == f"{path}: invalid configuration ({len(case.expected)} error(s)):"
    printed = issue_lines(proc.stderr)
    assert len(printed) == len(case.expected)
    for expected, line in zip(case.expected, printed, strict=True):
        assert matches(expected, line), (expected, line)


def test_check_good_configs_exit_0():
    proc = cli_in_process("check", "configs/mock_arm.toml", "configs/mock_humanoid.toml")
    assert proc.returncode == 0, proc.stderr
    assert_no_traceback(proc)
    out = proc.stdout.splitlines()
    assert len(out) == 2
    assert out[0].startswith("configs/mock_arm.toml: ok: robot mock_arm, 7 joints, drivers: arm (mock, 7 joints)")
    assert out[1].startswith("configs/mock_humanoid.toml: ok: robot mock_humanoid, 33 joints, drivers: legs (mock, 12 joints)")


def test_check_continues_after_a_bad_config(tmp_path):
    bad = write(tmp_path, MANY.toml)
    proc = cli_in_process("check", bad, "configs/mock_arm.toml")
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


@pytest.mark.parametrize(
    "args, message",
    [
        (("--rate", "-5"), "argument --rate: must be more than 0 Hz (got -5)"),
        (("--rate", "nan"), "argument --rate: must be a finite number of Hz (got nan)"),
        (("--rate", "inf"), "argument --rate: must be a finite number of Hz (got inf)"),
        (("--duration", "nan"), "argument --duration: must be a finite number of seconds (got nan)"),
        (("--duration", "inf"), "argument --duration: must be a finite number of seconds (got inf)"),
        (("--duration", "1e300"), "argument --duration: must be at most 1e+09 s (got 1e300)"),
        (("--duration", "-1"), "argument --duration: must be more than 0 s (got -1)"),
        (("--duration", "0"), "argument --duration: must be more than 0 s (got 0)"),
        (("--duration", "ten"), "argument --duration: 'ten' is not a number"),
        (("--spin-guard-us", "-5"), "argument --spin-guard-us: must be 0 or more µs (got -5)"),
        (("--spin-guard-us", "nan"), "argument --spin-guard-us: must be a finite number of µs (got nan)"),
    ],
    ids=lambda v: " ".join(v) if isinstance(v, tuple) else "",
)
def test_bad_run_option_exits_2_naming_the_option(tmp_path, args, message):
    report = tmp_path / "report.json"
    proc = cli_in_process("configs/mock_arm.toml", *args, "--report-json", report)
    assert proc.returncode == 2
    assert_no_traceback(proc)
    assert message in proc.stderr.splitlines()[-1], proc.stderr
    assert proc.stdout == ""
    assert not report.exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (("--rate", "60000"), "--rate (loop.rate_hz): input should be less than or equal to 50000 (got 60000.0)"),
        (("--rate", "0.01"), "--rate (loop.rate_hz): input should be greater than or equal to 0.1 (got 0.01)"),
    ],
)
def test_run_option_out_of_the_config_range_exits_2_naming_the_option(args, message):
    proc = cli_in_process("configs/mock_arm.toml", *args, "--duration", "0.1")
    assert proc.returncode == 2
    assert_no_traceback(proc)
    assert proc.stderr.splitlines()[0] == "configs/mock_arm.toml: invalid configuration (1 error(s)):"
    assert issue_lines(proc.stderr) == [message]


def test_schema_prints_valid_json():
    proc = cli_in_process("schema")
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
    assert proc.stdout.startswith("aiohal run report: mock_arm (7 joints, clock virtual on asyncio, overrun policy skip)")
    assert "ticks        300 in " in proc.stdout
    report = json.loads(report_path.read_text())
    assert set(report) >= REPORT_KEYS
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
    assert issue_lines(proc.stderr) == ["--spin-guard-us: realtime.spin_guard_us 800 is more than half the period"]
    assert_no_traceback(proc)


# ---------------------------------------------------------------- --report-json never destroys anything


def _report_targets(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    """Paths the report must not replace, each with a word of the reason printed."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    kept = tmp_path / "kept.json"
    kept.write_text("keep me\n")
    link = tmp_path / "link.json"
    link.symlink_to(kept)
    config = tmp_path / "robot.toml"
    config.write_text((ROOT / "configs" / "mock_arm.toml").read_text())
    return {
        "fifo": (fifo, "not a regular file"),
        "symlink": (link, "symbolic link"),
        "directory": (tmp_path, "directory"),
        "directory-with-slash": (Path(f"{tmp_path}/"), "directory"),
        "config": (config, "the config or a file it names"),
        "missing-directory": (tmp_path / "nowhere" / "report.json", "does not exist"),
        "device": (tmp_path / "null", "not a regular file"),
    }


@pytest.mark.parametrize(
    "target", ["fifo", "symlink", "directory", "directory-with-slash", "config", "missing-directory", "device"]
)
def test_report_json_refuses_what_it_would_destroy_before_starting(tmp_path, target):
    if target == "device":  # a device of its own: a regression must not replace /dev/null
        try:
            os.mknod(tmp_path / "null", 0o666 | stat.S_IFCHR, os.makedev(1, 3))
        except PermissionError:
            pytest.skip("making a device node needs root")
    path, reason = _report_targets(tmp_path)[target]
    config = tmp_path / "robot.toml"
    before = {p.name: (p.lstat().st_mode, p.read_text() if p.is_file() else None) for p in tmp_path.iterdir()}
    proc = run_cli(config, "--duration", "0.1", "--clock", "virtual", "--report-json", path)
    assert proc.returncode == 2, proc.stderr
    assert_no_traceback(proc)
    assert proc.stderr.startswith("error: --report-json: ") and reason in proc.stderr, proc.stderr
    assert "starting robot" not in proc.stderr and proc.stdout == ""  # nothing started
    after = {p.name: (p.lstat().st_mode, p.read_text() if p.is_file() else None) for p in tmp_path.iterdir()}
    assert after == before  # nothing replaced, no temporary file left
    assert not Path(f"{tmp_path}.tmp").exists()


def test_report_json_replaces_a_regular_file_through_its_own_directory(tmp_path):
    report = tmp_path / "report.json"
    report.write_text("old\n")
    proc = run_cli("configs/mock_arm.toml", "--duration", "0.1", "--clock", "virtual", "--quiet",
                   "--report-json", report)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(report.read_text())["ticks"] == 100
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]  # no temporary file left


def test_report_json_that_became_unwritable_during_the_run_loses_only_the_file(tmp_path):
    from aiohal.core.run_report import write_json

    gone = tmp_path / "gone"
    gone.mkdir()
    gone.rmdir()
    with pytest.raises(ValueError, match="does not exist"):
        write_json({"ticks": 1}, gone / "report.json")


# ---------------------------------------------------------------- configs that are not configs


@pytest.mark.parametrize(
    "make, reason",
    [
        (lambda tmp: Path("/dev/zero"), "not a regular file (a character device)"),
        (lambda tmp: write(tmp, "# padding\n" * 110_000), "larger than 1 MiB"),
        (lambda tmp: write(tmp, "x = " + "[" * 50_000 + "]" * 50_000 + "\n"), "nest more than 32 levels"),
        (lambda tmp: write(tmp, "x = " + "[" * 40 + "]" * 40 + "\n"), "nest more than 32 levels"),
        (lambda tmp: write(tmp, "x = " + "{a = " * 40 + "1" + "}" * 40 + "\n"), "nest more than 32 levels"),
    ],
    ids=["dev-zero", "over-1-MiB", "50000-nested-arrays", "40-nested-arrays", "40-nested-tables"],
)
def test_check_refuses_a_file_too_big_or_too_deep(tmp_path, make, reason):
    path = make(tmp_path)
    # capped address space: a regression that reads /dev/zero to the end fails, not the machine
    proc = subprocess.run(
        [sys.executable, "-c", "import resource, sys, runpy; resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30)); "
         "sys.argv = ['aiohal', 'check', sys.argv[1]]; runpy.run_module('aiohal', run_name='__main__')", str(path)],
        cwd=ROOT, capture_output=True, text=True, timeout=TIMEOUT,
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert_no_traceback(proc)
    assert issue_lines(proc.stderr) == [issue for issue in issue_lines(proc.stderr) if reason in issue]
    assert len(issue_lines(proc.stderr)) == 1


# ---------------------------------------------------------------- the report reads right

ONE_JOINT = """
[robot]
name = "one"

[joints.j0]
velocity = 2.0

[[driver]]
type = "mock"
joints = ["j0"]

[controller]
type = "sine"
"""


@pytest.mark.parametrize("event_loop", ["asyncio", "uvloop"])
def test_the_report_reads_as_plain_words_with_units(tmp_path, event_loop):
    proc = run_cli(write(tmp_path, ONE_JOINT), "--duration", "0.2", "--clock", "virtual", "--loop", event_loop)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert f"(1 joint, clock virtual on {event_loop}," in out
    assert "deadlines missed 0 (passed while a tick was late), ticks over the period" in out
    assert "  safety       ran normally; at the end: drivers closed  (stop: duration reached)" in out
    assert "WARNING" not in out  # nothing is wrong with a chosen virtual clock
    assert re.search(r"controller   sine: tracking rms \S+, tracking max \S+$", out, re.M), out
    assert "[mock] closed, 1 joint," in out
    for repr_text in ("None", "[]", "{", "True", "False", "_"):  # no Python reprs, no raw keys
        assert repr_text not in out.split("aiohal run report:")[1].replace("p99.9", ""), (repr_text, out)


def test_quiet_prints_nothing_when_nothing_is_wrong(tmp_path):
    report = tmp_path / "report.json"
    proc = run_cli(write(tmp_path, ONE_JOINT), "--duration", "0.1", "--clock", "virtual", "--quiet",
                   "--log-format", "json", "--report-json", report)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "" and proc.stderr == ""
    assert json.loads(report.read_text())["ticks"] == 100


# ---------------------------------------------------------------- the simulators' command lines


@pytest.mark.parametrize(
    "module, args, message",
    [
        ("aiohal.drivers.hands.robotiq_sim", ["--port", "70000"], "argument --port: must be from 0 to 65535 (got 70000)"),
        ("aiohal.drivers.hands.robotiq_sim", ["--port", "-1"], "argument --port: must be from 0 to 65535 (got -1)"),
        ("aiohal.drivers.hands.robotiq_sim", ["--device-id", "300"], "argument --device-id: must be from 1 to 247"),
        ("aiohal.drivers.hands.robotiq_sim", ["--object", "nan"], "argument --object: must be from 0 to 1 (got nan)"),
        ("aiohal.drivers.hands.robotiq_sim", ["--activation-time", "-1"], "argument --activation-time: must be from 0"),
        ("aiohal.drivers.ethercat.sim", ["--ifname", "an-interface-name-too-long"],
         "argument --ifname: 'an-interface-name-too-long' is not a Linux interface name"),
        ("aiohal.drivers.ethercat.sim", ["--ifname", ""], "argument --ifname: '' is not a Linux interface name"),
        ("aiohal.drivers.udp.sim", ["--dynamics", "rigid"], "argument --dynamics: invalid choice: 'rigid'"),
        ("aiohal.drivers.udp.sim", ["--dynamics", "servo", "--servo-json", '{"gear_ratio": 0}'],
         "argument --servo-json: gear_ratio: input should be greater than 0"),
        ("aiohal.drivers.udp.sim", ["--servo-json", "{}"], "argument --servo-json: only with --dynamics servo"),
        ("aiohal.drivers.fri.sim", ["--remote", "127.0.0.1:9", "--dynamics", "servo", "--servo-json", "{gear"],
         "argument --servo-json: the value: invalid JSON"),
        ("aiohal.drivers.fri.sim", ["--remote", "127.0.0.1:9", "--dynamics", "servo", "--servo-json", '{"gear": 1}'],
         "argument --servo-json: gear: extra inputs are not permitted"),
    ],
    ids=lambda v: " ".join(v) if isinstance(v, list) else None,
)
def test_simulator_command_lines_refuse_bad_arguments(module, args, message):
    proc = subprocess.run([sys.executable, "-m", module, *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=TIMEOUT)
    assert proc.returncode == 2, proc.stderr
    assert_no_traceback(proc)
    assert message in proc.stderr.splitlines()[-1], proc.stderr


def test_robotiq_sim_on_a_port_in_use_says_so(tmp_path):
    import socket

    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        proc = subprocess.run([sys.executable, "-m", "aiohal.drivers.hands.robotiq_sim", "--port", str(port)],
                              cwd=ROOT, capture_output=True, text=True, timeout=TIMEOUT)
    assert proc.returncode == 1, proc.stderr
    assert_no_traceback(proc)
    assert proc.stderr.splitlines()[-1].startswith(f"error: cannot serve on 127.0.0.1:{port}: "), proc.stderr


def test_readme_commands_run_with_the_python_that_has_aiohal():
    # `python -m aiohal...` needs the Python aiohal is installed in: the README names .venv's
    readme = (ROOT / "README.md").read_text()
    commands = re.findall(r"([^\s`]*python3?) -m (aiohal[\w.]*)", readme)
    assert commands
    assert {python for python, _ in commands} == {".venv/bin/python"}, commands
    for module in sorted({module for _, module in commands}):
        proc = subprocess.run([sys.executable, "-m", module, "--help"], cwd=ROOT, capture_output=True, text=True,
                              timeout=TIMEOUT)
        assert proc.returncode == 0, (module, proc.stderr)


def test_pyproject_declares_its_license_as_spdx():
    # a table or a License classifier makes setuptools warn on every install
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == "MIT"
    assert not [c for c in project["classifiers"] if c.startswith("License ::")]


def test_make_bench_quick_exists_and_the_readme_says_how_long_bench_takes():
    makefile = (ROOT / "Makefile").read_text()
    recipe = re.search(r"^bench-quick:.*\n((?:\t.*\n)+)", makefile, re.M)
    assert recipe, "no bench-quick target"
    modules = re.findall(r"-m benchmarks\.(\w+)", recipe.group(1))
    assert modules and all((ROOT / "benchmarks" / f"{m}.py").exists() for m in modules)
    readme = (ROOT / "README.md").read_text()
    assert "`make bench-quick`" in readme
    assert re.search(r"`make bench` runs .* takes about half an\s+hour \(31 min", readme, re.S)


@pytest.mark.parametrize("flag", [None, "--no-panel"])
def test_the_live_panel_reports_its_cost_and_no_panel_turns_only_it_off(tmp_path, flag):
    """On a terminal the panel is drawn, and the report says how long drawing took;
    ``--no-panel`` leaves it out and keeps the report."""
    import pty

    report = tmp_path / "report.json"
    main, terminal = pty.openpty()
    proc = subprocess.Popen(
        [sys.executable, "-m", "aiohal", str(ROOT / "configs" / "mock_arm.toml"), "--duration", "1.2",
         "--report-json", str(report), *([flag] if flag else [])],
        cwd=ROOT, stdout=terminal, stderr=subprocess.PIPE, text=True,
    )
    os.close(terminal)
    shown = b""
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline:  # bounded: read the terminal while the run writes to it
            ready, _, _ = select.select([main], [], [], 0.5)
            if ready:
                try:
                    chunk = os.read(main, 1 << 16)
                except OSError:  # EIO: the run ended and closed its side
                    break
                if not chunk:
                    break
                shown += chunk
            elif proc.poll() is not None:
                break
        _, err = proc.communicate(timeout=60)
    finally:
        os.close(main)
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    data = json.loads(report.read_text())
    assert b"aiohal run report" in shown  # the report is printed either way
    if flag:
        assert "status_panel" not in data
    else:
        panel = data["status_panel"]
        assert panel["refreshes"] >= 1 and 0 < panel["draw_ms_mean"] <= panel["draw_ms_max"]
        assert b"panel        " in shown


def test_help_lists_every_command_and_a_mistyped_one_is_named():
    helped = run_cli("--help")
    assert helped.returncode == 0
    for command in ("run", "check", "schema", "plugins", "info", "replay", "plot"):
        assert re.search(rf"^\s+(\[run\]|{command}) ", helped.stdout, re.M), command
    typo = run_cli("chek", ROOT / "configs" / "mock_arm.toml")
    assert typo.returncode == 2
    assert "unknown command 'chek' (did you mean 'check'?)" in typo.stderr and "Traceback" not in typo.stderr


def test_a_report_figure_with_parts_gives_each_its_unit():
    from aiohal.core.run_report import _item

    assert _item("rtt_us", {"p50": 6.1, "p99": 153.7}) == "rtt (p50 6.10 µs, p99 153.70 µs)"
    assert _item("sm_watchdog_ms", [50.0, 100.0]) == "sm watchdog 50.00 ms; 100.00 ms"
    assert _item("cycles", 12) == "cycles 12"


def test_the_report_json_is_written_when_bring_up_fails(tmp_path):
    config = tmp_path / "robot.toml"
    config.write_text((ROOT / "configs" / "mock_arm.toml").read_text().replace(
        'dynamics = "first_order"', 'dynamics = "first_order"\nfaults = { open_error = true }'))
    report = tmp_path / "report.json"
    proc = run_cli(config, "--duration", "1", "--clock", "virtual", "--report-json", report)
    assert proc.returncode == 1
    data = json.loads(report.read_text())
    assert data["drivers"]["arm"]["status"] == "failed"
    assert [(f["source"], f["phase"]) for f in data["faults"]] == [("driver:arm", "open")]


def test_every_shipped_config_checks():
    configs = sorted((ROOT / "configs").glob("*.toml"))
    proc = cli_in_process("check", *configs)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count(": ok: robot ") == len(configs)
