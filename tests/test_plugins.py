"""Plugins: built-ins and entry points, lazy import, clear errors for missing dependencies."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import arm_raw

from aiohal import plugins
from aiohal.config import parse_config
from aiohal.errors import AiohalError, ConfigError, MissingDependencyError, PluginError

ROOT = Path(__file__).resolve().parent.parent
TIMEOUT = 30

PLUGIN_SOURCE = '''\
"""A third-party plugin, installed only through its dist-info entry points."""

import numpy as np

from aiohal.hal import Controller, Driver, Options


class FakeOptions(Options):
    gain: float = 1.0


class FakeDriver(Driver):
    Options = FakeOptions

    async def read(self):
        np.copyto(self.view.state.position, self.view.command.position)
        self.view.mark_fresh()

    async def write(self):
        pass


class FakeController(Controller):
    def update(self, t, dt):
        pass

    def metrics(self):
        return {"fake": True}


def helper():
    """Not a plugin: a function registered by mistake."""
'''

ENTRY_POINTS = """\
[aiohal.drivers]
fake = fakehal_plugin:FakeDriver
broken = fakehal_broken:Driver
mock = fakehal_plugin:FakeDriver
a_function = fakehal_plugin:helper
options_not_driver = fakehal_plugin:FakeOptions
a_driver_with_a_rather_long_name = fakehal_plugin:FakeDriver

[aiohal.controllers]
fakectl = fakehal_plugin:FakeController
driver_as_controller = fakehal_plugin:FakeDriver
"""

FAKE_CONFIG = """\
[robot]
name = "fake_bot"

[loop]
rate_hz = 500
clock = "virtual"

[joints.j0]
velocity = 1.0

[joints.j1]
velocity = 1.0

[[driver]]
type = "fake"
joints = ["j0", "j1"]

[driver.options]
gain = 2.5

[controller]
type = "fakectl"
"""


@pytest.fixture
def plugin_dir(tmp_path: Path) -> Path:
    """A folder that, on PYTHONPATH, makes an installed distribution with aiohal entry points."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "fakehal_plugin").mkdir()
    (site / "fakehal_plugin" / "__init__.py").write_text(PLUGIN_SOURCE)
    (site / "fakehal_broken.py").write_text("import definitely_missing_dep_xyz\n\nDriver = None\n")
    dist = site / "fakehal_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: fakehal-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(ENTRY_POINTS)
    return site


def run_cli(*args, pythonpath: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(pythonpath)}
    return subprocess.run(
        [sys.executable, "-m", "aiohal", *map(str, args)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=TIMEOUT,
    )


def _row(stdout: str, name: str) -> str:
    rows = [line for line in stdout.splitlines() if line.split()[:1] == [name]]
    assert len(rows) == 1, (name, stdout)
    return rows[0]


# ---------------------------------------------------------------- real entry points


def test_plugins_lists_entry_points_and_broken_ones(plugin_dir):
    proc = run_cli("plugins", pythonpath=plugin_dir)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    out = proc.stdout
    drivers, controllers = out.split("controllers:\n")
    assert drivers.startswith("drivers:\n")

    fake = _row(drivers, "fake")
    assert fake.split() == ["fake", "entry", "point", "(fakehal-plugin)", "ok"]
    fakectl = _row(controllers, "fakectl")
    assert fakectl.split() == ["fakectl", "entry", "point", "(fakehal-plugin)", "ok"]

    broken = _row(drivers, "broken")
    assert "entry point (fakehal-plugin)" in broken
    assert broken.endswith(
        "unavailable: driver \"broken\" needs the optional dependency 'definitely_missing_dep_xyz': "
        "install the package that provides 'definitely_missing_dep_xyz'"
    )

    # the built-ins are still there and load
    assert _row(controllers, "sine").split()[-1] == "ok"
    mock_rows = [line for line in drivers.splitlines() if line.split()[:1] == ["mock"]]
    assert len(mock_rows) == 2
    assert mock_rows[0].split() == ["mock", "built-in", "ok"]
    # an entry point cannot take over a built-in name
    assert mock_rows[1].split()[:5] == ["mock", "entry", "point", "(fakehal-plugin)", "ignored:"]
    assert mock_rows[1].endswith("ignored: a built-in has this name")


def test_plugins_without_entry_points_lists_only_builtins(tmp_path):
    proc = run_cli("plugins", pythonpath=tmp_path)
    assert proc.returncode == 0
    names = [line.split()[0] for line in proc.stdout.splitlines() if line.startswith("  ")]
    assert names == ["canopen", "ethercat", "fri", "mock", "mujoco", "nrt_hand", "replay", "udp", "chirp", "circle", "gait", "hold", "homing", "sequence",
                     "sine", "stream"]


def test_entry_point_driver_and_controller_work_from_a_config(plugin_dir, tmp_path):
    config = tmp_path / "fake.toml"
    config.write_text(FAKE_CONFIG)
    proc = run_cli("check", config, pythonpath=plugin_dir)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == (
        f"{config}: ok: robot fake_bot, 2 joints, drivers: fake (fake, 2 joints), controller fakectl at 500 Hz"
    )


def test_entry_point_plugin_options_are_validated(plugin_dir, tmp_path):
    config = tmp_path / "fake.toml"
    config.write_text(FAKE_CONFIG.replace("gain = 2.5", "gian = 2.5"))
    proc = run_cli("check", config, pythonpath=plugin_dir)
    assert proc.returncode == 2
    assert '  driver[0].options.gian: unknown key (did you mean "gain"?)' in proc.stderr.splitlines()


def test_broken_entry_point_in_a_config_is_a_config_error(plugin_dir, tmp_path):
    config = tmp_path / "broken.toml"
    config.write_text(FAKE_CONFIG.replace('type = "fake"', 'type = "broken"').replace("[driver.options]\ngain = 2.5\n", ""))
    proc = run_cli("check", config, pythonpath=plugin_dir)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert (
        "  driver[0].type: driver \"broken\" needs the optional dependency 'definitely_missing_dep_xyz': "
        "install the package that provides 'definitely_missing_dep_xyz'"
    ) in proc.stderr.splitlines()


def test_entry_point_plugins_run(plugin_dir, tmp_path):
    config = tmp_path / "fake.toml"
    config.write_text(FAKE_CONFIG)
    proc = run_cli(config, "--duration", "0.1", "--report-json", tmp_path / "r.json", "--quiet",
                   pythonpath=plugin_dir)
    assert proc.returncode == 0, proc.stderr
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["ticks"] == 50
    assert report["controller"] == {"type": "fakectl", "fake": True}
    assert report["drivers"]["fake"]["type"] == "fake"
    assert report["faults"] == []


# ---------------------------------------------------------------- in process


@pytest.fixture
def fresh_cache():
    plugins.load.cache_clear()
    yield
    plugins.load.cache_clear()


def test_unknown_plugin_is_a_lookup_error_listing_available(fresh_cache):
    with pytest.raises(PluginError) as info:
        plugins.load("driver", "nope")
    assert isinstance(info.value, LookupError) and isinstance(info.value, AiohalError)
    assert not isinstance(info.value, MissingDependencyError)
    known = ", ".join(sorted(plugins.available("driver")))
    assert "mock" in known
    assert str(info.value) == f'unknown driver "nope" (available: {known})'

    with pytest.raises(LookupError, match=r'^unknown controller "nope" \(available: chirp, circle, gait, hold, homing, sequence, sine'):
        plugins.load("controller", "nope")


def test_builtins_load_lazily():
    code = (
        "import sys; from aiohal import plugins; plugins.available('driver'); plugins.available('controller');"
        "print(sorted(m for m in sys.modules if m.startswith(('aiohal.drivers.', 'aiohal.controllers.'))));"
        "plugins.load('driver', 'mock');"
        "print(sorted(m for m in sys.modules if m.startswith(('aiohal.drivers.', 'aiohal.controllers.'))))"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=TIMEOUT)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == ["[]", "['aiohal.drivers.mock', 'aiohal.drivers.mock_fast']"]


@pytest.fixture
def fake_builtins(tmp_path, monkeypatch, fresh_cache):
    """Built-ins whose modules fail in the ways a real optional driver can."""
    (tmp_path / "fakehal_needs_sim.py").write_text("import definitely_missing_sim_xyz\n\nSimDriver = None\n")
    (tmp_path / "fakehal_no_attr.py").write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    table = {kind: dict(entries) for kind, entries in plugins.BUILTIN.items()}
    table["driver"]["simfake"] = ("fakehal_needs_sim:SimDriver", "sim")
    table["driver"]["nomodule"] = ("fakehal_module_that_is_absent:Driver", "sim")
    table["driver"]["noattr"] = ("fakehal_no_attr:Driver", None)
    monkeypatch.setattr(plugins, "BUILTIN", table)
    yield
    for name in ("fakehal_needs_sim", "fakehal_no_attr"):
        sys.modules.pop(name, None)


def test_missing_optional_dependency_names_the_extra(fake_builtins):
    with pytest.raises(MissingDependencyError) as info:
        plugins.load("driver", "simfake")
    exc = info.value
    assert isinstance(exc, PluginError) and isinstance(exc, ImportError) and isinstance(exc, LookupError)
    assert 'pip install "aiohal[sim]"' in str(exc)
    assert str(exc) == (
        "driver \"simfake\" needs the optional dependency 'definitely_missing_sim_xyz': "
        'install the extra: pip install "aiohal[sim]"'
    )
    assert isinstance(exc.__cause__, ModuleNotFoundError)
    # catchable as a plain ImportError too
    plugins.load.cache_clear()
    with pytest.raises(ImportError):
        plugins.load("driver", "simfake")


def test_missing_plugin_module_is_not_a_missing_dependency(fake_builtins):
    with pytest.raises(PluginError) as info:
        plugins.load("driver", "nomodule")
    assert not isinstance(info.value, MissingDependencyError)
    assert str(info.value) == "driver \"nomodule\": module 'fakehal_module_that_is_absent' not found"


def test_missing_plugin_attribute(fake_builtins):
    with pytest.raises(PluginError, match=r'^driver "noattr": fakehal_no_attr:Driver does not exist$'):
        plugins.load("driver", "noattr")


def test_describe_reports_broken_plugins_without_raising(fake_builtins):
    rows = {spec.name: (spec, error) for spec, error in plugins.describe("driver")}
    assert rows["mock"][1] is None
    assert rows["simfake"][0].source == "built-in" and rows["simfake"][0].extra == "sim"
    assert 'pip install "aiohal[sim]"' in rows["simfake"][1]
    assert "not found" in rows["nomodule"][1]
    assert "does not exist" in rows["noattr"][1]


def test_config_using_a_driver_with_a_missing_dependency(fake_builtins):
    raw = arm_raw()
    raw["driver"][0]["type"] = "simfake"
    with pytest.raises(ConfigError) as info:
        parse_config(raw)
    assert [str(i) for i in info.value.issues] == [
        "driver[0].type: driver \"simfake\" needs the optional dependency 'definitely_missing_sim_xyz': "
        'install the extra: pip install "aiohal[sim]"'
    ]


def test_load_is_cached(fresh_cache):
    first = plugins.load("controller", "sine")
    assert plugins.load("controller", "sine") is first
    assert plugins.load.cache_info().hits >= 1


# ---------------------------------------------------------------- entry points that are not plugins


NOT_PLUGINS = {
    ("driver", "a_function"): "fakehal_plugin:helper is a function, not a subclass of aiohal.Driver",
    ("driver", "options_not_driver"): "fakehal_plugin:FakeOptions is the class FakeOptions, not a subclass of aiohal.Driver",
    ("controller", "driver_as_controller"): "fakehal_plugin:FakeDriver is the class FakeDriver, not a subclass of aiohal.Controller",
}


def test_an_entry_point_that_is_not_a_plugin_class_is_listed_unavailable(plugin_dir):
    proc = run_cli("plugins", pythonpath=plugin_dir)
    assert proc.returncode == 0, proc.stderr
    drivers, controllers = proc.stdout.split("controllers:\n")
    for (kind, name), reason in NOT_PLUGINS.items():
        row = _row(drivers if kind == "driver" else controllers, name)
        assert row.endswith(f'unavailable: {kind} "{name}": {reason}'), row
    assert _row(drivers, "a_driver_with_a_rather_long_name").endswith(" ok")
    # one table: the source and status columns start at the same place on every row
    rows = [re.fullmatch(r"  \S+ +(built-in|entry point \(\S+\)) +(ok|unavailable: .*|ignored: .*)", line)
            for line in proc.stdout.splitlines() if line.startswith("  ")]
    assert all(rows), proc.stdout
    assert len({m.start(1) for m in rows}) == 1 and len({m.start(2) for m in rows}) == 1, proc.stdout


@pytest.mark.parametrize("kind, name", list(NOT_PLUGINS), ids=[n for _, n in NOT_PLUGINS])
def test_a_config_using_a_non_plugin_entry_point_is_a_config_error(plugin_dir, tmp_path, kind, name):
    config = tmp_path / "robot.toml"
    text = FAKE_CONFIG.replace('type = "fake"', f'type = "{name}"').replace("[driver.options]\ngain = 2.5\n", "") \
        if kind == "driver" else FAKE_CONFIG.replace('type = "fakectl"', f'type = "{name}"')
    config.write_text(text)
    proc = run_cli("check", config, pythonpath=plugin_dir)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    where = "driver[0].type" if kind == "driver" else "controller.type"
    assert f'  {where}: {kind} "{name}": {NOT_PLUGINS[kind, name]}' in proc.stderr.splitlines(), proc.stderr


def test_schema_works_and_offers_only_loadable_plugins(plugin_dir):
    proc = run_cli("schema", pythonpath=plugin_dir)
    assert proc.returncode == 0, proc.stderr
    schema = json.loads(proc.stdout)
    driver_types = schema["$defs"]["DriverSection"]["properties"]["type"]["enum"]
    controller_types = schema["properties"]["controller"]["properties"]["type"]["enum"]
    assert "fake" in driver_types and "a_driver_with_a_rather_long_name" in driver_types
    assert "fakectl" in controller_types
    for _kind, name in NOT_PLUGINS:
        assert name not in driver_types + controller_types
    assert "broken" not in driver_types  # a missing dependency: not a choice either
