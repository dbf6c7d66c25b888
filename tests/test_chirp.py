"""The ``chirp`` controller's logarithmic sweep, and the frequency-response analysis of
benchmarks/lola_bandwidth.py recovering a known system."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import arm_raw, virtual_loop

from aiohal.config import parse_config
from aiohal.errors import ConfigError
from benchmarks.lola_bandwidth import bandwidth_3db, transfer_function

RATE = 5000.0  # ten samples per period at the sweep's 500 Hz end


def chirp_raw(**params) -> dict:
    raw = arm_raw(1, type="chirp", params=params)
    raw["loop"]["rate_hz"] = RATE
    raw["joints"]["j0"]["acceleration"] = 1e4  # A·(2π·500 Hz)² ≈ 2000 rad/s² at the end
    return raw


def crossing_frequencies(t: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Times halfway between successive zero crossings of x, and 1 / (2 · their spacing)."""
    i = np.flatnonzero(np.sign(x[:-1]) * np.sign(x[1:]) < 0)
    crossings = t[i] - x[i] * (t[i + 1] - t[i]) / (x[i + 1] - x[i])
    return (crossings[1:] + crossings[:-1]) / 2, 0.5 / np.diff(crossings)


@pytest.mark.asyncio
async def test_the_sweep_rises_exponentially_from_f_start_to_f_end():
    duration, settle, ramp = 1.0, 0.1, 0.05
    loop = virtual_loop(chirp_raw(duration=duration, settle=settle, ramp=ramp))
    sent = []
    loop.add_publisher(lambda lp: sent.append((lp.robot.clock.tick / RATE, lp.robot.command.position[0],
                                               lp.robot.command.velocity[0])))
    async with loop:
        report = await loop.run(duration=settle + duration + 0.05)
    assert not report["faults"] and report["commands_refused"] == 0
    t, position, velocity = np.array(sent).T
    q0 = position[0]
    s = t - t[0] - settle  # time into the sweep (the controller's t is 0 at the first tick)
    sweep = (s > ramp) & (s < duration - ramp)  # at full amplitude
    mid, f = crossing_frequencies(s[sweep], position[sweep] - q0)
    expected = 10.0 * 50.0 ** (mid / duration)
    np.testing.assert_allclose(f, expected, rtol=0.01)
    # ln f is a line in time: at the sweep's start 10 Hz, at its end 500 Hz (the defaults)
    assert mid[0] < 0.15 and mid[-1] > duration - 0.1
    slope, intercept = np.polyfit(mid, np.log(f), 1)
    assert math.exp(intercept) == pytest.approx(10.0, rel=0.01)
    assert math.exp(intercept + slope * duration) == pytest.approx(500.0, rel=0.01)
    # the target velocity is the sweep's: its peaks are 2π·f·A
    peak = np.abs(velocity[sweep & (s > duration - 0.1)]).max()
    assert peak == pytest.approx(2 * math.pi * 500.0 * 50.0 ** (-0.05 / duration) * 0.0002, rel=0.02)
    # still at the start position before, and back on it after
    assert np.all(position[s < -1e-9] == q0) and np.all(position[s > duration + 1e-9] == q0)
    assert np.abs(position - q0).max() <= 0.0002 + 1e-12


@pytest.mark.asyncio
async def test_position_only_sends_no_target_velocity():
    loop = virtual_loop(chirp_raw(duration=0.2, settle=0.0, velocity_feedforward=False))
    moved, velocity = [], []
    loop.add_publisher(lambda lp: (moved.append(lp.robot.command.position[0]), velocity.append(lp.robot.command.velocity[0])))
    async with loop:
        await loop.run(duration=0.2)
    assert np.ptp(moved) > 1e-4 and not np.any(velocity)


@pytest.mark.parametrize(("params", "key"), [
    ({"f_start": 100.0, "f_end": 50.0}, "controller.params.f_end"),
    ({"amplitude": 0.01}, "controller.params.amplitude"),  # 2π·500·0.01 = 31 rad/s > 2
    ({"amplitude": {"j9": 0.001}}, "controller.params.amplitude"),
    ({"duration": 0.05, "ramp": 0.05}, "controller.params.ramp"),
])
def test_a_bad_sweep_names_its_key(params, key):
    with pytest.raises(ConfigError) as info:
        parse_config(chirp_raw(**params))
    assert key in str(info.value)


def first_order_response(u: np.ndarray, cutoff: float, fs: float) -> np.ndarray:
    """y[k + 1] = α·y[k] + (1 − α)·u[k]: a first-order lag of the given cut-off, sampled."""
    alpha = math.exp(-2 * math.pi * cutoff / fs)
    y = np.zeros_like(u)
    for k in range(len(u) - 1):
        y[k + 1] = alpha * y[k] + (1 - alpha) * u[k]
    return y


@pytest.mark.parametrize("cutoff", [25.0, 60.0, 150.0])
def test_the_analysis_recovers_a_first_order_systems_bandwidth(cutoff):
    fs, duration, f0, f1 = 2000.0, 4.0, 10.0, 500.0
    t = np.arange(round((duration + 1.0) * fs)) / fs
    s = np.clip(t - 0.5, 0.0, duration)
    rate = math.log(f1 / f0) / duration
    u = np.where((t >= 0.5) & (t <= 0.5 + duration), 2e-4 * np.sin(2 * math.pi * f0 / rate * np.expm1(rate * s)), 0.0)
    y = first_order_response(u, cutoff, fs)
    f, gain, coherence = transfer_function(u[:-1], y[1:], fs, segment=round(fs))
    bandwidth = bandwidth_3db(f, gain, 11.0, 450.0)
    assert bandwidth == pytest.approx(cutoff, rel=0.03)
    band = (f >= 11.0) & (f <= 450.0)
    assert coherence[band].min() > 0.99  # a linear system without noise
    # and the gain an octave either side is the sampled lag's, (1 − α) / |1 − α·e^(−jωT)|
    alpha = math.exp(-2 * math.pi * cutoff / fs)
    for octave in (0.5, 2.0):
        i = np.argmin(np.abs(f - octave * cutoff))
        exact = (1 - alpha) / abs(1 - alpha * np.exp(-2j * math.pi * f[i] / fs))
        assert abs(gain[i]) == pytest.approx(exact, rel=0.02)


def test_a_gain_that_never_falls_has_no_bandwidth_in_the_band():
    f = np.array([10.0, 100.0, 1000.0])
    assert bandwidth_3db(f, np.array([1.0, 0.9, 0.8]), 10.0, 1000.0) is None
    # the crossing is interpolated on log f: -3 dB halfway between -0 and -6 dB in dB
    gain = 10 ** (np.array([0.0, -6.0206, -20.0]) / 20)
    assert bandwidth_3db(f, gain, 10.0, 1000.0) == pytest.approx(math.sqrt(10.0 * 100.0), rel=1e-3)
