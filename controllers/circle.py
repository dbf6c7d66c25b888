"""``circle``: every configured end-effector site traces a Cartesian circle (R-HAL's experiment).

The same class and parameters serve every robot: kinematics come from the robot's own MJCF
model through MuJoCo (site positions and Jacobians), so only the site names change between
a 7-DOF arm and a 33-DOF humanoid.

Each tick, damped-least-squares differential IK moves the *commanded* configuration q*:
``dq = Jᵀ (J Jᵀ + λ² I)⁻¹ (ẋ_d + K (x_d - x(q*))) · dt``, clipped to the joint velocity
limits and kept inside the joint ranges; the command is q* with velocity dq/dt. The circle's
centre is the start position plus ``offset`` (by default the start lies on the circle), and
the target ramps in from the start pose with a minimum-jerk blend over ``ramp`` seconds;
``center`` places it in world coordinates instead.

It says when it cannot do its job: at start, a circle farther from the first joint of a site's
chain than the chain's links reach is an error, and a start pose whose Jacobian cannot move
the site in the circle's plane is a warning (``start_warning`` in the report); while it runs,
a tracking error above ``max_error_m`` is a fault (the loop holds the robot).

The tracking error is measured on the robot: the site position computed from the *measured*
joint positions against the target the previous command was made for. RMS and max after the
ramp are reported as ``rms_error_m`` and ``max_error_m``.
"""

from __future__ import annotations

import itertools
import logging
import math
import os
from typing import Literal

import mujoco
import numpy as np
from pydantic import Field, model_validator

from aiohal.config import ConfigPath
from aiohal.hal import Controller, Options
from aiohal.mjcf import joint_addresses, load_model, model_names
from aiohal.robot import Mode

log = logging.getLogger(__name__)

PLANES = {"xy": (0, 1), "yz": (1, 2), "xz": (0, 2)}

#: below this singular value (m/rad) of a site's Jacobian in the circle's plane, the start
#: pose is singular: the IK's first steps go nowhere (a straight arm: 0)
SINGULAR_M_PER_RAD = 1e-3

Point = tuple[float, float, float]


class CircleParams(Options):
    sites: list[str] = Field(min_length=1, description="End-effector sites of the model.")
    radius: float = Field(0.1, gt=0, description="Circle radius (m).")
    period: float = Field(5.0, gt=0, description="Time for one turn (s).")
    plane: Literal["xy", "yz", "xz"] = Field("yz", description="Plane of the circle (world axes).")
    offset: Point | None = Field(
        None, description="Centre minus start position (m); default: -radius along the plane's first axis."
    )
    center: Point | list[Point] | None = Field(
        None, description="Centre in world coordinates (m), one for every site or one per site; instead of offset."
    )
    max_error_m: float = Field(
        0.05, gt=0, description="Tracking error (m) above which the controller faults and the robot holds."
    )
    ramp: float = Field(1.0, ge=0, description="Blend from the start pose onto the circle (s).")
    damping: float = Field(0.02, gt=0, description="Damped least squares λ (m).")
    gain: float = Field(20.0, ge=0, description="Task-space feedback on the commanded pose (1/s).")
    joints: list[str] | None = Field(None, description="Joints the IK may move; default: every joint.")
    model: ConfigPath | None = Field(None, description="MJCF model; default: [robot] model.")

    @model_validator(mode="after")
    def _one_centre(self) -> CircleParams:
        if self.offset is not None and self.center is not None:
            raise ValueError("give center or offset, not both")
        if isinstance(self.center, list) and len(self.center) != len(self.sites):
            raise ValueError(f"center: {len(self.center)} points for {len(self.sites)} sites (one, or one per site)")
        return self


class CircleController(Controller):
    Params = CircleParams
    params: CircleParams

    @classmethod
    def check_config(cls, params, joints, robot):
        path = params.model or robot.model
        where = "params.model" if params.model else "/robot.model"  # the key that named the file
        if path is None:
            return [("params.model", "no model: set params.model or [robot] model")]
        if not os.path.exists(path):
            return [(where, f"file not found: {path}")]
        try:
            names = model_names(str(path))
        except ValueError as exc:
            return [(where, str(exc))]
        issues = []
        for i, site in enumerate(params.sites):
            if site not in names.sites:
                issues.append((f"params.sites[{i}]", f'site "{site}" is not in the model {os.path.basename(path)}'))
        robot_joints = {j.name for j in joints}
        for name in params.joints or [j.name for j in joints]:
            if name not in robot_joints:
                issues.append(("params.joints", f'unknown joint "{name}"'))
            elif name not in names.joints:
                issues.append(("params.joints", f'joint "{name}" is not in the model {os.path.basename(path)}'))
        return issues

    def configure(self, robot, params) -> None:
        super().configure(robot, params)
        self.model = load_model(params.model or robot.model_path)
        self.data = mujoco.MjData(self.model)
        names = list(params.joints or robot.joint_names)
        self.rows = robot.indices(names)  # the robot's rows the IK moves
        # a run of rows (every joint, usually) is a slice: q*'s rows are then a view, not a gather
        self._gather = not np.array_equal(self.rows, np.arange(self.rows[0], self.rows[0] + len(self.rows)))
        if not self._gather:
            self.rows = slice(int(self.rows[0]), int(self.rows[0]) + len(self.rows))
        self.qpos_adr, self.dof_adr = joint_addresses(self.model, names)
        all_qpos, _ = joint_addresses(self.model, list(robot.joint_names))
        # a fixed-base model usually stores the joints in order: write them as one slice
        first = int(all_qpos[0])
        contiguous = np.array_equal(all_qpos, np.arange(first, first + len(all_qpos)))
        self.all_qpos = slice(first, first + len(all_qpos)) if contiguous else all_qpos
        self.site_ids = np.array(
            [mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, s) for s in params.sites], dtype=np.intp
        )
        sites = len(self.site_ids)
        m, n = 3 * sites, len(names)
        self._jac_full = np.zeros((3, self.model.nv))
        self.J = np.zeros((m, n))
        self._A = np.zeros((m, m))
        self._w = np.zeros(m)
        self._x = np.zeros(m)
        self._err = np.zeros(m)
        self._task = np.zeros(m)
        self._x_d = np.zeros(m)
        self._v_d = np.zeros(m)
        self._tmp = np.zeros(m)
        self._dq = np.zeros(n)
        self._reg = (params.damping**2) * np.eye(m)
        self.q_min = robot.position_min[self.rows]
        self.q_max = robot.position_max[self.rows]
        self.max_step = robot.velocity_limit[self.rows] * 0.95
        a, b = PLANES[params.plane]
        u, v = np.zeros(3), np.zeros(3)
        u[a], v[b] = 1.0, 1.0
        self.u = u
        self.U = np.tile(u, sites)  # the plane's axes, once per site
        self.V = np.tile(v, sites)
        self.omega = 2.0 * math.pi / params.period

    # ------------------------------------------------------------ lifecycle

    def start(self, t: float) -> None:
        robot = self.robot
        self.t0 = t
        self.q_cmd = robot.state.position.copy()  # IK integrates the commanded configuration
        self.x_start = np.zeros(3 * len(self.site_ids))
        site_positions = _kinematics(self)
        site_positions(self.q_cmd, self.x_start, True)  # the Jacobian too, for _check_start
        params = self.params
        if params.center is not None:
            center = np.array(params.center, dtype=float)
            self.center = np.tile(center, len(self.site_ids)) if center.ndim == 1 else center.ravel()
        else:
            offset = np.array(params.offset) if params.offset is not None else -params.radius * self.u
            self.center = self.x_start + np.tile(offset, len(self.site_ids))
        self.start_warning = _check_start(self)  # raises if a circle is out of reach
        if self.start_warning:
            log.warning("circle: %s", self.start_warning)
        self._error = [0.0, 0.0, 0]  # tracking: sum of squares, largest square, samples
        robot.command.mode[:] = Mode.POSITION
        robot.command.velocity[:] = 0.0
        self._tick = _tick_function(self, site_positions)

    def update(self, t: float, dt: float) -> None:
        self._tick(t, dt)

    def metrics(self) -> dict:
        sum_sq, max_sq, samples = getattr(self, "_error", (0.0, 0.0, 0))
        warning = {"start_warning": self.start_warning} if getattr(self, "start_warning", "") else {}
        if not samples:
            return {"rms_error_m": None, "max_error_m": None, "samples": 0, **warning}
        return {
            "rms_error_m": round(math.sqrt(sum_sq / samples), 6),
            "max_error_m": round(math.sqrt(max_sq), 6),
            "samples": samples,
            **warning,
        }


def _check_start(c: CircleController) -> str:
    """Raise ValueError for a circle no pose can reach; a warning for a singular start pose.

    Reach: along a site's chain of moving joints, the distance between consecutive joint
    anchors does not change with the pose, so their sum (plus the site's distance from the last
    anchor, plus the travel of slide joints) bounds how far from the first anchor the site gets.
    Run once, before the first tick (its SVD may start BLAS's threads: not on the tick).
    """
    model, data, p = c.model, c.data, c.params
    moving = {int(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)) for n in (p.joints or c.robot.joint_names)}
    angles = np.linspace(0.0, 2.0 * math.pi, 73)
    a, b = PLANES[p.plane]
    warnings = []
    for i, (name, sid) in enumerate(zip(p.sites, c.site_ids, strict=True)):
        chain = []  # moving joints from the site's body to the root
        body = int(model.site_bodyid[sid])
        while body > 0:
            first = int(model.body_jntadr[body])
            chain += [j for j in range(first + int(model.body_jntnum[body]) - 1, first - 1, -1) if j in moving]
            body = int(model.body_parentid[body])
        if not chain:
            raise ValueError(f'site "{name}": no joint the circle may move carries it')
        anchors = [data.xanchor[j] for j in reversed(chain)] + [data.site_xpos[sid]]
        reach = sum(float(np.linalg.norm(q - r)) for r, q in itertools.pairwise(anchors))
        reach += sum(
            float(np.ptp(model.jnt_range[j])) for j in chain if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE
        )
        points = np.repeat(c.center[3 * i : 3 * i + 3][None, :], len(angles), axis=0)
        points[:, a] += p.radius * np.cos(angles)
        points[:, b] += p.radius * np.sin(angles)
        farthest = float(np.linalg.norm(points - anchors[0], axis=1).max())
        if farthest > reach + 1e-9:
            joint = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, chain[-1])
            raise ValueError(
                f'site "{name}": the circle comes {farthest:.3f} m from joint "{joint}", '
                f"farther than the chain reaches ({reach:.3f} m)"
            )
        in_plane = c.J[3 * i : 3 * i + 3][[a, b]]  # the site's Jacobian rows of the circle's axes
        smallest = float(np.linalg.svd(in_plane, compute_uv=False).min())
        if smallest < SINGULAR_M_PER_RAD:
            warnings.append(
                f'site "{name}": the start pose is singular in the {p.plane} plane '
                f"(smallest singular value {smallest:.2g} m/rad); the circle may be tracked "
                "poorly: start from another pose (initial_position or keyframe)"
            )
    return "; ".join(warnings)


# The tick's work is a closure over the controller's arrays, built once at start(): every
# attribute lookup and method frame costs more than its line, and more still on the caches
# the step and the wait left cold; it keeps the overhead benchmark's WALK-MAN ratio under
# 1.10 (docs/performance.md). tests/test_circle.py compares it with a plain formulation.


def _kinematics(c: CircleController):
    """``site_positions(q_all, out, jacobian)``: forward kinematics at joint positions
    ``q_all`` (robot order) into ``out``, and the site Jacobians into ``c.J`` if asked."""
    model, data = c.model, c.data
    qpos, site_xpos = data.qpos, data.site_xpos
    all_qpos, site_ids, dof_adr, jac, J = c.all_qpos, c.site_ids, c.dof_adr, c._jac_full, c.J
    blocks = [(int(sid), J[3 * i : 3 * i + 3]) for i, sid in enumerate(site_ids)]
    kinematics, com_pos, jac_site = mujoco.mj_kinematics, mujoco.mj_comPos, mujoco.mj_jacSite

    def site_positions(q_all: np.ndarray, out: np.ndarray, jacobian: bool) -> None:
        qpos[all_qpos] = q_all
        kinematics(model, data)
        site_xpos.take(site_ids, axis=0, out=out.reshape(-1, 3))
        if jacobian:
            com_pos(model, data)
            for sid, rows in blocks:
                jac_site(model, data, jac, None, sid)
                jac.take(dof_adr, axis=1, out=rows)

    return site_positions


def _tick_function(c: CircleController, site_positions):
    """``update(t, dt)`` of a started controller."""
    p = c.params
    radius, omega, ramp, gain = p.radius, c.omega, p.ramp, p.gain
    allowed_sq = p.max_error_m**2
    t0, center, x_start, U, V, reg = c.t0, c.center, c.x_start, c.U, c.V, c._reg
    J, A, w, dq, x, err, task, x_d, v_d, tmp = c.J, c._A, c._w, c._dq, c._x, c._err, c._task, c._x_d, c._v_d, c._tmp
    q_min, q_max, max_step, rows, q_cmd = c.q_min, c.q_max, c.max_step, c.rows, c.q_cmd
    gather = c._gather
    q = np.zeros(len(max_step)) if gather else q_cmd[rows]  # q*'s moving rows: a view unless gathered
    last_target = x_start.copy()  # the target the last command was made for
    sites = len(c.site_ids)
    error = c._error
    measured = c.robot.state.position
    command_position = c.robot.command.position
    command_velocity = c.robot.command.velocity
    velocity_rows = None if gather else command_velocity[rows]  # a view of the moving rows
    subtract, multiply, add, minimum, maximum, copyto = (
        np.subtract,
        np.multiply,
        np.add,
        np.minimum,
        np.maximum,
        np.copyto,
    )
    cos, sin = math.cos, math.sin
    mul_mat_mat_t, chol_factor, chol_solve, mul_mat_t_vec = (
        mujoco.mju_mulMatMatT,
        mujoco.mju_cholFactor,
        mujoco.mju_cholSolve,
        mujoco.mju_mulMatTVec,
    )

    def update(t: float, dt: float) -> None:
        elapsed = t - t0
        # tracking: the measured pose against the target the last command was made for
        if elapsed > ramp:
            site_positions(measured, x, False)
            subtract(x, last_target, out=err)
            multiply(err, err, out=err)
            sum_sq, max_sq = error[0], error[1]
            for e in err.reshape(-1, 3).sum(axis=1):
                sum_sq += e
                if e > max_sq:
                    max_sq = e
            error[0], error[1] = sum_sq, max_sq
            error[2] += sites
            if max_sq > allowed_sq:
                raise RuntimeError(f"tracking error {math.sqrt(max_sq):.3f} m exceeds max_error_m {p.max_error_m:g} m")
        # target: x = centre + r(cos·U + sin·V),  v = rω(-sin·U + cos·V)
        phase = omega * elapsed
        c, s = cos(phase), sin(phase)
        multiply(U, radius * c, out=x_d)
        multiply(V, radius * s, out=tmp)
        add(x_d, tmp, out=x_d)
        add(x_d, center, out=x_d)
        multiply(U, -radius * omega * s, out=v_d)
        multiply(V, radius * omega * c, out=tmp)
        add(v_d, tmp, out=v_d)
        if elapsed < ramp:  # blend from the start pose: x = start + b(t)·(circle - start)
            r = elapsed / ramp
            b = r * r * r * (10.0 + r * (-15.0 + 6.0 * r))
            db = 30.0 * r * r * (1.0 - r) * (1.0 - r) / ramp
            subtract(x_d, x_start, out=tmp)
            multiply(v_d, b, out=v_d)
            add(v_d, db * tmp, out=v_d)
            multiply(tmp, b, out=tmp)
            add(x_start, tmp, out=x_d)
        site_positions(q_cmd, x, True)
        # task velocity: feed-forward plus feedback on the commanded pose
        subtract(x_d, x, out=task)
        multiply(task, gain, out=task)
        add(task, v_d, out=task)
        # dq = Jᵀ (J Jᵀ + λ² I)⁻¹ task · dt, with MuJoCo's small dense routines: no BLAS call
        # on the tick (its first call starts a thread pool and costs milliseconds)
        mul_mat_mat_t(A, J, J)
        add(A, reg, out=A)
        chol_factor(A, 0.0)
        chol_solve(w, A, task)
        mul_mat_t_vec(dq, J, w)
        multiply(dq, dt, out=dq)
        limit = max_step * dt
        minimum(dq, limit, out=dq)
        maximum(dq, -limit, out=dq)
        if gather:
            q_cmd.take(rows, out=q)
        add(q, dq, out=q)
        minimum(q, q_max, out=q)
        maximum(q, q_min, out=q)
        if gather:
            q_cmd[rows] = q
        copyto(command_position, q_cmd)
        if dt > 0:
            if gather:
                multiply(dq, 1.0 / dt, out=dq)
                command_velocity[rows] = dq
            else:
                multiply(dq, 1.0 / dt, out=velocity_rows)
        copyto(last_target, x_d)

    return update
