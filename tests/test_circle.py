"""The ``circle`` type's tick (a closure over its arrays, with MuJoCo's small dense routines)
against the plain controller it is written from and the damped-least-squares step in numpy."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest
from conftest import CONFIGS, require_module
from hypothesis import given, settings
from hypothesis import strategies as st

mujoco = require_module("mujoco")

from aiohal import plugins
from aiohal.config import parse_config
from aiohal.controllers.circle import CircleController
from aiohal.controllers.circle_fast import FastCircleController
from aiohal.core.loop import ControlLoop
from aiohal.core.ticker import VirtualTickSource


def plain_step(c, q_all: np.ndarray, elapsed: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """One IK step as the module's docstring states it: the next q* (robot order) and the
    velocity command of the moving rows."""
    p = c.params
    data = mujoco.MjData(c.model)
    data.qpos[:] = c.data.qpos
    data.qpos[c.all_qpos] = q_all
    mujoco.mj_kinematics(c.model, data)
    mujoco.mj_comPos(c.model, data)
    x = data.site_xpos[c.site_ids].ravel()
    jacobians = []
    for sid in c.site_ids:
        jac = np.zeros((3, c.model.nv))
        mujoco.mj_jacSite(c.model, data, jac, None, int(sid))
        jacobians.append(jac[:, c.dof_adr])
    J = np.vstack(jacobians)

    phase = c.omega * elapsed
    x_d = c.center + p.radius * (math.cos(phase) * c.U + math.sin(phase) * c.V)
    v_d = p.radius * c.omega * (-math.sin(phase) * c.U + math.cos(phase) * c.V)
    if elapsed < p.ramp:  # minimum-jerk blend from the start pose
        r = elapsed / p.ramp
        b = r**3 * (10 - 15 * r + 6 * r**2)
        db = 30 * r**2 * (1 - r) ** 2 / p.ramp
        v_d = b * v_d + db * (x_d - c.x_start)
        x_d = c.x_start + b * (x_d - c.x_start)
    task = v_d + p.gain * (x_d - x)
    dq = J.T @ np.linalg.solve(J @ J.T + p.damping**2 * np.eye(len(x)), task) * dt
    limit = c.max_step * dt
    dq = np.clip(dq, -limit, limit)
    q_next = q_all.copy()
    q_next[c.rows] = np.clip(q_all[c.rows] + dq, c.q_min, c.q_max)
    return q_next, dq / dt


def kuka_raw(controller: str) -> dict:
    raw = tomllib.loads((CONFIGS / "kuka_lwr_sim.toml").read_text())
    raw["controller"]["type"] = controller
    # the test sets the tick's time and pose at will: far from the circle, not a tracking fault
    raw["controller"]["params"]["max_error_m"] = 100.0
    return raw


@pytest.fixture(scope="module")
def started():
    """A lockstep KUKA loop, activated and run for a few ticks: its controller started."""
    import asyncio

    config = parse_config(kuka_raw("circle"), base_dir=CONFIGS).with_loop(clock="virtual")
    loop = ControlLoop(config, tick_source=VirtualTickSource())
    runner = asyncio.new_event_loop()
    runner.run_until_complete(loop.__aenter__())
    runner.run_until_complete(loop.run(ticks=5))
    yield loop
    runner.run_until_complete(loop.__aexit__(None, None, None))
    runner.close()


@settings(max_examples=40, deadline=None)
@given(elapsed=st.floats(0.0, 12.0), dt=st.sampled_from([0.001, 0.002, 0.004]),
       nudge=st.lists(st.floats(-0.05, 0.05), min_size=7, max_size=7))
def test_the_circle_tick_matches_the_plain_formulation(started, elapsed, dt, nudge):
    c = started.controller
    assert isinstance(c, FastCircleController)
    command = started.robot.command
    q_cmd = c.q_cmd
    q_cmd += np.array(nudge)  # any commanded configuration near the start pose
    before = q_cmd.copy()
    expected_q, expected_v = plain_step(c, before, elapsed, dt)
    c.update(c.t0 + elapsed, dt)
    np.testing.assert_allclose(command.position, expected_q, rtol=0, atol=1e-10)
    np.testing.assert_allclose(command.velocity[c.rows], expected_v, rtol=0, atol=1e-7)
    np.copyto(q_cmd, before - np.array(nudge))  # back near the start for the next example


def run_kuka(controller: str, ticks: int) -> tuple[np.ndarray, dict]:
    """The KUKA circle in lockstep: the final measured position and the controller's report."""
    import asyncio

    async def run():
        config = parse_config(kuka_raw(controller), base_dir=CONFIGS).with_loop(clock="virtual")
        async with ControlLoop(config, tick_source=VirtualTickSource()) as loop:
            report = await loop.run(ticks=ticks)
            return loop.robot.state.position.copy(), report["controller"]

    return asyncio.run(run())


def test_the_circle_type_runs_the_plain_controller_closed_up():
    plugins.register("controller", "plain_circle", CircleController)
    try:
        plain_q, plain = run_kuka("plain_circle", 1500)  # past the 1 s ramp: tracking counts
    finally:
        plugins.unregister("controller", "plain_circle")
    fast_q, fast = run_kuka("circle", 1500)
    assert plain["samples"] == fast["samples"] > 0
    np.testing.assert_allclose(fast_q, plain_q, rtol=0, atol=1e-9)
    assert fast["rms_error_m"] == pytest.approx(plain["rms_error_m"], abs=1e-6)
    assert fast["max_error_m"] == pytest.approx(plain["max_error_m"], abs=1e-6)
