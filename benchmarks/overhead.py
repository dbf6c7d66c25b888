"""What the HAL costs (R-HAL, Table I): CPU per tick of an aiohal run against a hand-written
loop with no HAL doing the same robot work, in lockstep.

Robots: the four simulated robots of the R-HAL experiment (``configs/kuka_lwr_sim.toml``
7 joints, ``centauro_upper_sim`` 15, ``coman_sim`` 29, ``walkman_sim`` 33: MuJoCo driver,
``circle`` controller), and two mock robots with ``hold``: ``configs/mock_humanoid.toml``
(33 joints on 4 mock drivers with first-order dynamics, IMU, F/T sensors, hands) and a
33-joint robot on one mock driver (mirror dynamics, built like ``tests/helpers.arm_raw``).

Both sides run in lockstep: the aiohal run on the virtual clock (``ControlLoop`` as the CLI
runs it, back to back), the no-HAL loop as a plain ``for`` loop. CPU per tick = process CPU
time (user + system, ``getrusage``) over the measured ticks / ticks, after a warm-up of
``--warmup`` seconds in the same process, both with the start-up heap collected and frozen
(aiohal does this itself in ``activate()`` and ``run()``; the collection is outside the measured
ticks). CPU % at
1 kHz is that time over the 1 ms period: what a real-time 1 kHz run would use at that cost
per tick (the wait itself is not included). Each side runs ``--repeat`` times in fresh
processes, alternately; the table gives the ratio of the medians, the range of the ratios of
the pairs run back to back, and the ratio of the fastest runs (the least disturbed by the
host on a shared VM).

The no-HAL loop (``--worker`` kind ``nohal_mujoco`` / ``nohal_mock`` of this module) reads
its numbers (joints, limits, gains, sites, initial pose) from the same TOML at set-up, then
each tick touches only plain numpy arrays and MuJoCo. It does:

* MuJoCo robots: read q and q̇ (``qpos``/``qvel`` ``take``); the circle controller's
  operations in the order of ``controllers/circle_fast.py`` (tracking error by forward kinematics
  of the measured q after the ramp, minimum-jerk target, forward kinematics and site
  Jacobians of q* on the controller's own MjData, ``mju`` damped-least-squares solve, step
  clipped to 0.95 × the velocity limit, q* kept in range); the torque law of
  ``drivers/mujoco.py`` (``kp·(q* − q) + kd·(q̇* − q̇) + qfrc_bias``, clipped to the actuator
  range, written to ``ctrl``); ``mj_step`` with the same substeps.
* Mock robots: the mock driver's simulated joints per driver slice (first-order or mirror
  step, effort echo, the hands' scalar motion) and ``hold``'s two array writes.

aiohal's MuJoCo driver does the same joint arithmetic in compiled (numba) kernels, bit for
bit (``drivers/mujoco_kernels.py``); the no-HAL loop writes it with numpy, as a Python user
without the HAL would, and so does aiohal's mock driver.

It does not: await anything or run an event loop; check feedback age, command modes or
finiteness; clamp commands to the joint limits (the circle's own clip stays, it is the
controller's math); keep stamps, fresh ticks or per-phase timings; copy IMU/F/T sensor data or
measured effort into device arrays; copy q* into a separate command array (the IK updates q*
in place; the circle gathers and scatters its rows only when they are not a run of the
robot's); add the
zero effort and feed-forward commands into the torque. The trajectories are compared at the
end (final measured q, and the circle's RMS tracking error): equal values show that both
loops did the same robot work.

With ``--interleave TICKS`` both loops are built in one process and run alternately, TICKS
ticks at a time (which side goes first alternates), for ``--seconds``; each round's ratio then
compares the two sides measured milliseconds apart. The table also gives the ratio in the
quarter of rounds where the no-HAL side ran fastest and in the quarter where it ran slowest,
to show whether the ratio moves with the host's speed (on this VM the host's speed changes
by 2x within minutes). On a shared VM whose speed changes by
1.5x from one minute to the next, separate runs pair a fast run with a slow one (pairs of
0.8-2.5 for the same code); the rounds' median and quartiles do not. Each aiohal round is one
``run()``, whose fixed cost (about 0.4 ms: the stall watchdog's thread started and joined)
falls on the aiohal side: about 0.7 µs per tick at 500 ticks, more for shorter rounds.

``--clock realtime`` (with ``--interleave``) runs both sides at 1 kHz on real deadlines instead,
as R-HAL's Table I measured a robot running: aiohal on its timerfd, the no-HAL loop with
``time.sleep`` to absolute deadlines (the cheapest wait a Python loop has: one syscall per
tick). CPU per tick then includes each side's wait and its cold start after it. Neither
side gets the configs' ``[realtime]`` settings, so neither needs privileges.

    python -m benchmarks.overhead [--seconds 5] [--warmup 1] [--repeat 5] [--only NAME ...]
        [--interleave TICKS [--clock virtual|realtime]] [--json PATH]
"""

from __future__ import annotations

import argparse
import gc
import math
import resource
import statistics
import time
from pathlib import Path

import numpy as np

from aiohal.core.tick_timing import PHASES

from .breakdown import load_raw, loop_spec, spawn, timeout_for, worker
from .common import ROOT, table, write_json
from .scaling import robot_raw

MODULE = "benchmarks.overhead"
CONFIGS = ROOT / "configs"
SIM = ["kuka_lwr_sim", "centauro_upper_sim", "coman_sim", "walkman_sim"]
MOCK = ["mock_humanoid_hold", "mock_33_hold"]


def _cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _measure(run_ticks, warmup: int, ticks: int) -> dict:
    """Warm up, then time ``ticks`` ticks: CPU and wall, like the loop's stats.begin/end."""
    gc.collect()
    gc.freeze()
    run_ticks(1, warmup + 1)
    cpu0, wall0 = _cpu_s(), time.monotonic_ns()
    run_ticks(warmup + 1, warmup + ticks + 1)
    wall = (time.monotonic_ns() - wall0) / 1e9
    cpu = _cpu_s() - cpu0
    gc.unfreeze()
    return {"cpu_s": cpu, "wall_s": wall, "ticks": ticks}


# ---------------------------------------------------------------- no HAL: MuJoCo + circle


def nohal_mujoco(spec: dict) -> dict:
    run_ticks, finish = setup_nohal_mujoco(spec)
    return {**_measure(run_ticks, spec["warmup_ticks"], spec["ticks"]), **finish()}


def setup_nohal_mujoco(spec: dict, phase_log: list | None = None):
    """The no-HAL MuJoCo loop, ready: (run_ticks(k_from, k_to), finish() -> final values).

    With ``phase_log`` each tick appends its (read, controller, torque, step) times in ns, as
    the HAL's loop times its phases (``--phases``)."""
    import mujoco

    from aiohal.config import load_config
    from aiohal.mjcf import actuator_for_joints, joint_addresses, load_model

    config = load_config(spec["config"])
    (dc,) = config.drivers
    opts, params = dc.options, config.controller.params
    assert dc.type == "mujoco" and config.controller.type == "circle" and params.joints is None
    names = [j.name for j in config.joints]
    n = len(names)
    period_s = config.period_ns / 1e9

    def per_joint(values) -> np.ndarray:
        if isinstance(values, dict):
            return np.array([float(values.get(j, 0.0)) for j in names])
        return np.full(n, float(values))

    q_min = np.array([j.position_min for j in config.joints])
    q_max = np.array([j.position_max for j in config.joints])
    v_max = np.array([j.velocity for j in config.joints])

    # the simulated robot, set up as drivers/mujoco.py does
    model = load_model(opts.model or config.robot.model)
    data = mujoco.MjData(model)
    mj_names = [opts.joint_map.get(j, j) for j in names]
    qpos_adr, dof_adr = joint_addresses(model, mj_names)
    actuators = actuator_for_joints(model, mj_names)
    substeps = round(period_s / model.opt.timestep)
    kp, kd = per_joint(opts.kp), per_joint(opts.kd)
    limited = model.actuator_ctrllimited[actuators].astype(bool)
    tau_min = np.where(limited, model.actuator_ctrlrange[actuators, 0], -np.inf)
    tau_max = np.where(limited, model.actuator_ctrlrange[actuators, 1], np.inf)
    start = per_joint(opts.initial_position)
    if opts.keyframe is not None:  # the keyframe's pose, except the joints initial_position names
        mujoco.mj_resetDataKeyframe(model, data, model.key(opts.keyframe).id)
        given = opts.initial_position if "initial_position" in opts.model_fields_set else {}
        if isinstance(given, dict):
            start = np.array([float(given.get(j, q)) for j, q in zip(names, data.qpos[qpos_adr], strict=True)])
    data.qpos[qpos_adr] = np.clip(start, q_min, q_max)
    mujoco.mj_forward(model, data)
    gravity = opts.gravity_compensation

    # the controller's own kinematic model, set up as controllers/circle_fast.py does
    kmodel = load_model(params.model or config.robot.model)
    kdata = mujoco.MjData(kmodel)
    k_qpos, k_dof = joint_addresses(kmodel, names)
    first = int(k_qpos[0])
    all_qpos = slice(first, first + n) if np.array_equal(k_qpos, np.arange(first, first + n)) else k_qpos
    site_ids = np.array([mujoco.mj_name2id(kmodel, mujoco.mjtObj.mjOBJ_SITE, s) for s in params.sites], dtype=np.intp)
    sites = len(site_ids)
    m = 3 * sites
    jac = np.zeros((3, kmodel.nv))
    J, A = np.zeros((m, n)), np.zeros((m, m))
    w, x, err, task, x_d, v_d, tmp = (np.zeros(m) for _ in range(7))
    reg = params.damping**2 * np.eye(m)
    max_step = v_max * 0.95
    a, b = {"xy": (0, 1), "yz": (1, 2), "xz": (0, 2)}[params.plane]
    u, vv = np.zeros(3), np.zeros(3)
    u[a], vv[b] = 1.0, 1.0
    U, V = np.tile(u, sites), np.tile(vv, sites)
    radius, omega, ramp, gain = params.radius, 2.0 * math.pi / params.period, params.ramp, params.gain

    q, qd, tau, ttmp, dq = (np.zeros(n) for _ in range(5))

    def fk(q_all: np.ndarray, out: np.ndarray, jacobian: bool) -> None:
        kdata.qpos[all_qpos] = q_all
        mujoco.mj_kinematics(kmodel, kdata)
        kdata.site_xpos.take(site_ids, axis=0, out=out.reshape(-1, 3))
        if jacobian:
            mujoco.mj_comPos(kmodel, kdata)
            for i, sid in enumerate(site_ids):
                mujoco.mj_jacSite(kmodel, kdata, jac, None, sid)
                jac.take(k_dof, axis=1, out=J[3 * i:3 * i + 3])

    # first read, then the circle's start(0)
    data.qpos.take(qpos_adr, out=q)
    q_cmd = q.copy()
    x_start = np.zeros(m)
    fk(q_cmd, x_start, False)
    offset = np.array(params.offset) if params.offset is not None else -radius * u
    center = x_start + np.tile(offset, sites)
    last_target = x_start.copy()
    acc = {"sum_sq": 0.0, "max": 0.0, "samples": 0}

    arrays = (q, qd, tau, ttmp, dq, q_cmd, x, err, task, x_d, v_d, tmp, A, w)

    timed, clock = phase_log is not None, time.perf_counter_ns

    def run_ticks(k_from: int, k_to: int) -> None:
        q, qd, tau, ttmp, dq, q_cmd, x, err, task, x_d, v_d, tmp, A, w = arrays  # locals, as in a hand-written loop
        sum_sq, max_err, samples = acc["sum_sq"], acc["max"], acc["samples"]
        for k in range(k_from, k_to):
            t = k * period_s
            dt = period_s
            if timed:
                t0 = clock()
            # read
            data.qpos.take(qpos_adr, out=q)
            data.qvel.take(dof_adr, out=qd)
            if timed:
                t1 = clock()
            # circle: tracking error of the measured pose
            if t > ramp:
                fk(q, x, False)
                np.subtract(x, last_target, out=err)
                err *= err
                for e in err.reshape(-1, 3).sum(axis=1):
                    sum_sq += e
                    if e > max_err:
                        max_err = e
                samples += sites
            # circle: target
            c, s = math.cos(omega * t), math.sin(omega * t)
            np.multiply(U, radius * c, out=x_d)
            np.multiply(V, radius * s, out=tmp)
            x_d += tmp
            x_d += center
            np.multiply(U, -radius * omega * s, out=v_d)
            np.multiply(V, radius * omega * c, out=tmp)
            v_d += tmp
            if t < ramp:
                r = t / ramp
                bl = r * r * r * (10.0 + r * (-15.0 + 6.0 * r))
                dbl = 30.0 * r * r * (1.0 - r) * (1.0 - r) / ramp
                np.subtract(x_d, x_start, out=tmp)
                v_d *= bl
                v_d += dbl * tmp
                tmp *= bl
                np.add(x_start, tmp, out=x_d)
            # circle: damped least squares on the commanded configuration
            fk(q_cmd, x, True)
            np.subtract(x_d, x, out=task)
            task *= gain
            task += v_d
            mujoco.mju_mulMatMatT(A, J, J)
            A += reg
            mujoco.mju_cholFactor(A, 0.0)
            mujoco.mju_cholSolve(w, A, task)
            mujoco.mju_mulMatTVec(dq, J, w)
            dq *= dt
            limit = max_step * dt
            np.minimum(dq, limit, out=dq)
            np.maximum(dq, -limit, out=dq)
            q_cmd += dq
            np.minimum(q_cmd, q_max, out=q_cmd)
            np.maximum(q_cmd, q_min, out=q_cmd)
            dq *= 1.0 / dt  # the velocity command
            np.copyto(last_target, x_d)
            if timed:
                t2 = clock()
            # the drive: PD + gravity compensation, then the physics
            np.subtract(q_cmd, q, out=tau)
            tau *= kp
            np.subtract(dq, qd, out=ttmp)
            ttmp *= kd
            tau += ttmp
            if gravity:
                tau += data.qfrc_bias.take(dof_adr, out=ttmp)
            np.minimum(tau, tau_max, out=tau)
            np.maximum(tau, tau_min, out=tau)
            data.ctrl[actuators] = tau
            if timed:
                t3 = clock()
            mujoco.mj_step(model, data, nstep=substeps)
            if timed:
                phase_log.append((t1 - t0, t2 - t1, t3 - t2, clock() - t3))
        acc["sum_sq"], acc["max"], acc["samples"] = sum_sq, max_err, samples

    def finish() -> dict:
        rms = math.sqrt(acc["sum_sq"] / acc["samples"]) if acc["samples"] else None
        return {"final_position": q.tolist(), "rms_error_m": rms}

    return run_ticks, finish


# ---------------------------------------------------------------- no HAL: mock + hold


def nohal_mock(spec: dict) -> dict:
    run_ticks, finish = setup_nohal_mock(spec)
    return {**_measure(run_ticks, spec["warmup_ticks"], spec["ticks"]), **finish()}


def setup_nohal_mock(spec: dict):
    """The no-HAL mock loop, ready: (run_ticks(k_from, k_to), finish() -> final values)."""
    from aiohal.config import parse_config

    config = parse_config(spec["raw"], base_dir=Path(spec["base_dir"]))
    assert config.controller.type == "hold"
    names = [j.name for j in config.joints]
    index = {name: i for i, name in enumerate(names)}
    n = len(names)
    period_s = config.period_ns / 1e9
    inv_dt = 1.0 / period_s
    q_min = np.array([j.position_min for j in config.joints])
    q_max = np.array([j.position_max for j in config.joints])
    kinds = {name: kind for name, kind, _ in config.devices}
    # the simulated robot: [position, velocity, effort]; and the command
    sim = np.zeros((3, n))
    pos, vel, eff = sim
    cmd_pos, cmd_vel, cmd_eff, cmd_ff = np.zeros((4, n))
    groups, hands = [], []
    for dc in config.drivers:
        assert dc.type == "mock"
        opts = dc.options
        s = slice(index[dc.joints[0]], index[dc.joints[-1]] + 1)
        init = opts.initial_position
        start = np.array([init.get(j, 0.0) if isinstance(init, dict) else init for j in dc.joints], dtype=float)
        pos[s] = np.clip(start, q_min[s], q_max[s])
        first_order = opts.dynamics == "first_order"
        alpha = 1.0 - math.exp(-period_s / opts.time_constant) if first_order else 1.0
        groups.append((pos[s], vel[s], eff[s], cmd_pos[s], cmd_eff[s], cmd_ff[s], first_order, alpha))
        for dev in dc.devices:
            if kinds[dev] == "hand":
                # grasp, speed, force, position, effort: HandGroup's initial values
                hands.append({"grasp": 0.0, "speed": 1.0, "force": 1.0, "position": 0.0, "effort": 0.0,
                              "rate": opts.hand_speed})
    np.copyto(cmd_pos, pos)  # activation: command := measured; hold keeps it (at rest: no braking)
    x_final = cmd_pos.copy()

    def run_ticks(k_from: int, k_to: int) -> None:
        cmd_vel_ = cmd_vel
        for _k in range(k_from, k_to):
            # the simulated joints move toward the command (mock's _step, per driver)
            for p, v, e, cp, ce, cf, first_order, alpha in groups:
                np.subtract(cp, p, out=v)
                if first_order:
                    v *= alpha
                p += v
                v *= inv_dt
                np.add(ce, cf, out=e)
            for hand in hands:
                step = hand["rate"] * hand["speed"] * period_s
                position = hand["position"]
                hand["position"] = min(max(hand["grasp"], position - step), position + step)
                hand["effort"] = hand["force"] if position > 0.0 else 0.0
            # hold
            np.copyto(cmd_pos, x_final)
            cmd_vel_[:] = 0.0

    return run_ticks, lambda: {"final_position": pos.tolist(), "rms_error_m": None}


# ---------------------------------------------------------------- both sides in one process


async def _interleaved(spec: dict) -> dict:
    """Both loops in one process, alternating in chunks of ``chunk`` ticks (the side that goes
    first alternates too): each round's ratio compares the two sides a few milliseconds
    apart, so a change of the host's speed between runs does not enter it."""
    from aiohal.config import parse_config
    from aiohal.core.loop import ControlLoop

    hal, bare = spec["hal"], spec["nohal"]
    chunk, rounds = spec["chunk"], spec["rounds"]
    realtime = spec.get("clock") == "realtime"
    phase_log: list | None = [] if spec.get("phases") and bare["kind"] == "nohal_mujoco" else None
    if bare["kind"] == "nohal_mujoco":
        run_ticks, finish = setup_nohal_mujoco(bare, phase_log)
    else:
        run_ticks, finish = setup_nohal_mock(bare)
    hal_phases: list[list[float]] = []  # per round: p50 µs of each HAL phase (PHASES order)
    bare_phases: list[list[float]] = []  # per round: p50 µs of read, controller, torque, step
    control = ControlLoop(parse_config(hal["raw"], base_dir=Path(hal["base_dir"])))
    await control.activate()
    k = 1

    missed = late = 0

    async def hal_chunk(ticks: int) -> float:
        nonlocal missed
        report = await control.run(ticks=ticks)  # freezes what is new on the heap before its first tick
        missed += report["missed_ticks"]
        stats = control.stats
        if phase_log is not None:
            hal_phases.append([float(v) / 1e3 for v in np.median(stats.phases[:, : stats.count], axis=1)])
        wall_s = (stats.stopped_wall_ns - stats.started_wall_ns) / 1e9
        return report["cpu_percent"] / 100.0 * wall_s / report["ticks"]

    def bare_chunk(ticks: int) -> float:
        nonlocal k, late
        gc.collect()  # as the loop does before its ticks
        gc.freeze()
        cpu0 = _cpu_s()
        if realtime:
            late += _at_deadlines(run_ticks, k, ticks, round(1e9 / hal["raw"]["loop"]["rate_hz"]))
        else:
            run_ticks(k, k + ticks)
        cpu = _cpu_s() - cpu0
        gc.unfreeze()
        k += ticks
        if phase_log:
            bare_phases.append([float(v) / 1e3 for v in np.median(np.array(phase_log), axis=0)])
            phase_log.clear()
        return cpu / ticks

    try:
        if hal["warmup_ticks"]:
            await hal_chunk(hal["warmup_ticks"])
            bare_chunk(bare["warmup_ticks"])
            hal_phases.clear()
            bare_phases.clear()
        pairs = []
        for r in range(rounds):
            if r % 2:
                b = bare_chunk(chunk)
                h = await hal_chunk(chunk)
            else:
                h = await hal_chunk(chunk)
                b = bare_chunk(chunk)
            pairs.append((h * 1e6, b * 1e6))
        final = np.asarray(control.robot.state.position).tolist()
        report = control.report()
    finally:
        await control.deactivate()
    return {"pairs": pairs, "final_position": final, "rms_error_m": report["controller"].get("rms_error_m"),
            "faults": len(report["faults"]), "missed": missed, "nohal_late": late, "nohal": finish(),
            "hal_phases_us": hal_phases, "nohal_phases_us": bare_phases}


def _quarters_by_host_speed(pairs: list[tuple[float, float]]) -> tuple[tuple[float, float], tuple[float, float]]:
    """(no-HAL µs, ratio) medians of the quarter of rounds where the no-HAL side ran fastest,
    and of the quarter where it ran slowest: how the ratio moves with the host's speed.

    Rounds are chosen by the no-HAL side's time alone. Where that time is low by chance, the
    ratio of the round comes out high, so the fastest quarter's ratio errs against aiohal."""
    by_speed = sorted(pairs, key=lambda pair: pair[1])
    n = max(1, len(by_speed) // 4)

    def medians(part: list[tuple[float, float]]) -> tuple[float, float]:
        return statistics.median(b for _, b in part), statistics.median(h / b for h, b in part)

    return medians(by_speed[:n]), medians(by_speed[-n:])


def _at_deadlines(run_ticks, k: int, ticks: int, period_ns: int) -> int:
    """The no-HAL loop in real time: sleep to each absolute deadline, then run one tick.
    Returns how many ticks started a period or more late (it runs them all, late)."""
    mono, sleep = time.monotonic_ns, time.sleep
    deadline = mono()
    late = 0
    for i in range(ticks):
        deadline += period_ns
        wait = deadline - mono()
        if wait > 0:
            sleep(wait / 1e9)
        elif wait <= -period_ns:
            late += 1
        run_ticks(k + i, k + i + 1)
    return late


def overhead_worker(spec: dict) -> dict:
    if spec["kind"] == "nohal_mujoco":
        return nohal_mujoco(spec)
    if spec["kind"] == "nohal_mock":
        return nohal_mock(spec)
    if spec["kind"] == "interleaved":
        import asyncio

        return asyncio.run(_interleaved(spec))
    return worker(spec)


# ---------------------------------------------------------------- the benchmark


def _cases(seconds: float, warmup: float, clock: str = "virtual") -> dict[str, tuple[dict, dict]]:
    """name -> (aiohal spec, no-HAL spec); ``clock`` virtual (lockstep) or timerfd."""
    ticks, warm = round(seconds * 1000), round(warmup * 1000)
    cases = {}
    for name in SIM:
        path = CONFIGS / f"{name}.toml"
        cases[name] = (
            loop_spec(_no_realtime(load_raw(path)), base_dir=path.parent, clock=clock, rate_hz=1000.0, seconds=seconds,
                      warmup=warmup),
            {"kind": "nohal_mujoco", "config": str(path), "warmup_ticks": warm, "ticks": ticks},
        )
    humanoid = CONFIGS / "mock_humanoid.toml"
    raw = load_raw(humanoid)
    raw["controller"] = {"type": "hold"}
    arm = robot_raw(33)
    for name, r, base in (("mock_humanoid_hold", raw, humanoid.parent), ("mock_33_hold", arm, ROOT)):
        spec = loop_spec(_no_realtime(r), base_dir=base, clock=clock, rate_hz=1000.0, seconds=seconds, warmup=warmup)
        cases[name] = (spec, {"kind": "nohal_mock", "raw": spec["raw"], "base_dir": str(base),
                              "warmup_ticks": warm, "ticks": ticks})
    return cases


def _no_realtime(raw: dict) -> dict:
    """The config without its [realtime] section: the no-HAL loop has none either (and a
    virtual clock never applies it)."""
    return {key: value for key, value in raw.items() if key != "realtime"}


def main() -> None:
    from .breakdown import worker_main

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=5.0, help="measured ticks, in seconds at 1 kHz (default 5)")
    p.add_argument("--warmup", type=float, default=1.0, help="warm-up seconds before the measured ticks")
    p.add_argument("--repeat", type=int, default=5, help="runs of each side, alternating (default 5)")
    p.add_argument("--only", nargs="*", default=None, help=f"cases to run (default: all of {SIM + MOCK})")
    p.add_argument("--interleave", type=int, default=0, metavar="TICKS",
                   help="run both sides in one process, alternating every TICKS ticks (default 0: separate runs)")
    p.add_argument("--clock", choices=("virtual", "realtime"), default="virtual",
                   help="virtual: lockstep, back to back (default); realtime: both sides at 1 kHz on real "
                        "deadlines (needs --interleave)")
    p.add_argument("--phases", action="store_true",
                   help="with --interleave: time the phases of both sides' ticks (MuJoCo robots; the no-HAL "
                        "loop then reads the clock 5 times per tick, so its CPU figures are not the headline)")
    p.add_argument("--json", default=None)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        worker_main(overhead_worker)
        return
    started = time.monotonic()
    if args.clock == "realtime" and args.interleave <= 0:
        p.error("--clock realtime needs --interleave TICKS")
    if args.phases and args.interleave <= 0:
        p.error("--phases needs --interleave TICKS")
    cases = _cases(args.seconds, args.warmup, "timerfd" if args.clock == "realtime" else "virtual")
    unknown = sorted(set(args.only or ()) - set(cases))
    if unknown:
        p.error(f"--only: unknown case(s) {', '.join(unknown)}; the cases are {', '.join(cases)}")
    if args.interleave > 0:
        _main_interleaved(args, cases, started)
        return
    rows, raw_results = [], {}
    for name in args.only or list(cases):
        hal_spec, nohal_spec = cases[name]
        hal_runs, bare_runs = [], []
        for _ in range(max(1, args.repeat)):
            hal_runs.append(spawn(MODULE, hal_spec, timeout_for(args.seconds * 5)))
            bare_runs.append(spawn(MODULE, nohal_spec, timeout_for(args.seconds * 5)))
        hal_us = [1e6 * r["cpu_s"] / r["report"]["ticks"] for r in hal_runs]
        bare_us = [1e6 * r["cpu_s"] / r["ticks"] for r in bare_runs]
        ratios = [h / b for h, b in zip(hal_us, bare_us, strict=True)]
        hal_med, bare_med = statistics.median(hal_us), statistics.median(bare_us)
        last_hal, last_bare = hal_runs[-1], bare_runs[-1]
        dq = float(np.max(np.abs(np.array(last_hal["final_position"]) - np.array(last_bare["final_position"]))))
        rms_hal = last_hal["report"]["controller"].get("rms_error_m")
        rms_bare = last_bare["rms_error_m"]
        faults = sum(len(r["report"]["faults"]) for r in hal_runs)
        rows.append({
            "robot": name, "joints": last_hal["report"]["joints"],
            "hal_us": round(hal_med, 1), "bare_us": round(bare_med, 1), "added_us": round(hal_med - bare_med, 1),
            "ratio": round(hal_med / bare_med, 3),
            "ratio_range": f"{min(ratios):.2f}–{max(ratios):.2f}",
            "ratio_min": round(min(hal_us) / min(bare_us), 3),
            "hal_cpu": round(hal_med / 10, 1), "bare_cpu": round(bare_med / 10, 1),
            "work_p50": statistics.median(r["report"]["work_us"]["p50"] for r in hal_runs),
            "rms": "–" if rms_hal is None else f"{rms_hal * 1e3:.3f} / {rms_bare * 1e3:.3f}",
            "dq": f"{dq:.1e}", "faults": faults,
        })
        raw_results[name] = {"aiohal_cpu_us_per_tick": hal_us, "nohal_cpu_us_per_tick": bare_us,
                             "aiohal_wall_us_per_tick": [1e6 * r["wall_s"] / r["report"]["ticks"] for r in hal_runs],
                             "nohal_wall_us_per_tick": [1e6 * r["wall_s"] / r["ticks"] for r in bare_runs],
                             "aiohal_phases_us": hal_runs[-1]["report"]["phases_us"]}
        print(f"{name}: done", flush=True)
    elapsed = time.monotonic() - started
    print()
    print(f"CPU per tick in lockstep, {args.seconds:g} s at 1 kHz after {args.warmup:g} s warm-up, "
          f"median of {args.repeat} runs each:")
    print(table(rows, [
        ("robot", "robot"), ("joints", "joints"), ("hal_us", "aiohal CPU µs/tick"), ("bare_us", "no-HAL CPU µs/tick"),
        ("added_us", "HAL adds µs/tick"), ("ratio", "ratio aiohal/no-HAL"), ("ratio_range", "range of pairs"), ("ratio_min", "ratio of minima"),
        ("hal_cpu", "CPU % at 1 kHz aiohal"), ("bare_cpu", "no-HAL"), ("work_p50", "aiohal work p50 µs"),
        ("rms", "RMS error mm aiohal / no-HAL"), ("dq", "final max |Δq| rad"), ("faults", "faults"),
    ]))
    print(f"\nelapsed {elapsed:.1f} s")
    write_json(args.json, {"seconds": args.seconds, "warmup": args.warmup, "repeat": args.repeat,
                           "elapsed_s": round(elapsed, 1), "rows": rows, "runs": raw_results})


def _phase_row(name: str, hal: list[list[float]], bare: list[list[float]]) -> dict:
    """Medians over the rounds of each side's per-round phase medians (µs), matched up: the
    HAL's write holds the driver's torque law and ``mj_step``; check and limits have no
    counterpart in the no-HAL loop."""
    h = dict(zip(PHASES, (statistics.median(col) for col in zip(*hal, strict=True)), strict=True))
    b_read, b_control, b_torque, b_step = (statistics.median(col) for col in zip(*bare, strict=True))

    def pair(x: float, y: float) -> str:
        return f"{x:.1f} / {y:.1f} ({x / y:.2f})"

    return {"robot": name, "rounds": len(hal), "read": pair(h["read"], b_read),
            "control": pair(h["control"], b_control), "write": pair(h["write"], b_torque + b_step),
            "hal_only": f"{h['check']:.1f} + {h['limits']:.1f} + {h['publish']:.1f}",
            "sum": pair(sum(h.values()), b_read + b_control + b_torque + b_step)}


def _main_interleaved(args, cases: dict, started: float) -> None:
    rows, raw_results, phase_rows = [], {}, []
    rounds = max(2, round(args.seconds * 1000 / args.interleave))
    for name in args.only or list(cases):
        hal_spec, nohal_spec = cases[name]
        spec = {"kind": "interleaved", "hal": hal_spec, "nohal": nohal_spec, "chunk": args.interleave, "rounds": rounds,
                "clock": args.clock, "phases": args.phases}
        runs = [spawn(MODULE, spec, timeout_for(args.seconds * 5)) for _ in range(max(1, args.repeat))]
        pairs = [pair for r in runs for pair in r["pairs"]]
        ratios = sorted(h / b for h, b in pairs)
        q25, q50, q75 = (float(np.percentile(ratios, q)) for q in (25, 50, 75))
        hal_med = statistics.median(h for h, _ in pairs)
        bare_med = statistics.median(b for _, b in pairs)
        fast, slow = _quarters_by_host_speed(pairs)
        last = runs[-1]
        dq = float(np.max(np.abs(np.array(last["final_position"]) - np.array(last["nohal"]["final_position"]))))
        rms_hal, rms_bare = last["rms_error_m"], last["nohal"]["rms_error_m"]
        rows.append({
            "robot": name, "joints": len(last["final_position"]), "rounds": len(pairs),
            "hal_us": round(hal_med, 1), "bare_us": round(bare_med, 1), "added_us": round(hal_med - bare_med, 1),
            "ratio": round(q50, 3), "iqr": f"{q25:.2f}–{q75:.2f}",
            "fast": f"{fast[0]:.1f} µs: {fast[1]:.2f}", "slow": f"{slow[0]:.1f} µs: {slow[1]:.2f}",
            "rms": "–" if rms_hal is None or rms_bare is None else f"{rms_hal * 1e3:.3f} / {rms_bare * 1e3:.3f}",
            "hal_cpu": round(hal_med / 10, 1), "bare_cpu": round(bare_med / 10, 1),
            "dq": f"{dq:.1e}", "faults": sum(r["faults"] for r in runs), "missed": sum(r["missed"] for r in runs),
            "late": sum(r["nohal_late"] for r in runs),
        })
        raw_results[name] = {"pairs_us": pairs}
        hal_ph = [row for r in runs for row in r["hal_phases_us"]]
        bare_ph = [row for r in runs for row in r["nohal_phases_us"]]
        if hal_ph and bare_ph:
            phase_rows.append(_phase_row(name, hal_ph, bare_ph))
            raw_results[name].update(hal_phases_us=hal_ph, nohal_phases_us=bare_ph)
        print(f"{name}: done", flush=True)
    elapsed = time.monotonic() - started
    print()
    how = "in lockstep" if args.clock == "virtual" else "at 1 kHz on real deadlines (wait included)"
    print(f"CPU per tick {how}, both sides in one process alternating every {args.interleave} ticks "
          f"({rounds} rounds per run, {args.repeat} runs): medians over the rounds")
    print(table(rows, [
        ("robot", "robot"), ("joints", "joints"), ("rounds", "rounds"), ("hal_us", "aiohal CPU µs/tick"),
        ("bare_us", "no-HAL CPU µs/tick"), ("added_us", "HAL adds µs/tick"), ("ratio", "ratio aiohal/no-HAL (median of rounds)"),
        ("iqr", "p25–p75 of rounds"), ("fast", "fastest quarter: no-HAL, ratio"),
        ("slow", "slowest quarter: no-HAL, ratio"), ("hal_cpu", "CPU % at 1 kHz aiohal"), ("bare_cpu", "no-HAL"),
        ("rms", "RMS error mm aiohal / no-HAL"), ("dq", "final max |Δq| rad"), ("missed", "aiohal missed ticks"),
        ("late", "no-HAL ticks ≥ 1 period late"),
        ("faults", "faults"),
    ]))
    if phase_rows:
        print("\nPhases, p50 µs per tick, aiohal / no-HAL (ratio), medians over the rounds; the no-HAL write is its "
              "torque law plus mj_step:")
        print(table(phase_rows, [
            ("robot", "robot"), ("rounds", "rounds"), ("read", "read"), ("control", "controller"),
            ("write", "write with the step"), ("hal_only", "aiohal only: check + limits + publish"),
            ("sum", "sum of the phases"),
        ]))
    print(f"\nelapsed {elapsed:.1f} s")
    write_json(args.json, {"seconds": args.seconds, "warmup": args.warmup, "repeat": args.repeat, "clock": args.clock,
                           "interleave": args.interleave, "phases": phase_rows, "elapsed_s": round(elapsed, 1), "rows": rows, "runs": raw_results})


if __name__ == "__main__":
    main()
