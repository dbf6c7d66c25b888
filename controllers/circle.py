"""``circle``: every configured end-effector site traces a Cartesian circle (R-HAL's experiment).

The same class and parameters serve every robot: kinematics come from the robot's own MJCF
model through MuJoCo (site positions and Jacobians), so only the site names change between
a 7-DOF arm and a 33-DOF humanoid.

Each tick, damped-least-squares differential IK moves the *commanded* configuration q*:
``dq = Jᵀ (J Jᵀ + λ² I)⁻¹ (ẋ_d + K (x_d - x(q*))) · dt``, clipped to the joint velocity
limits and kept inside the joint ranges; the command is q* with velocity dq/dt. The circle's
centre is the start position plus ``offset`` (by default the start lies on the circle), and
the target ramps in from the start pose with a minimum-jerk blend over ``ramp`` seconds.

The tracking error is measured on the robot: the site position computed from the *measured*
joint positions against the target the previous command was made for. RMS and max after the
ramp are reported as ``rms_error_m`` and ``max_error_m``.
"""

from __future__ import annotations

import math
import os
from typing import Literal

import mujoco
import numpy as np
from pydantic import Field

from aiohal.config import ConfigPath
from aiohal.hal import Controller, Options
from aiohal.robot import Mode

from aiohal.drivers.mujoco_model import joint_addresses, load_model, model_names

PLANES = {"xy": (0, 1), "yz": (1, 2), "xz": (0, 2)}


class CircleParams(Options):
    sites: list[str] = Field(min_length=1, description="End-effector sites of the model.")
    radius: float = Field(0.1, gt=0, description="Circle radius (m).")
    period: float = Field(5.0, gt=0, description="Time for one turn (s).")
    plane: Literal["xy", "yz", "xz"] = Field("yz", description="Plane of the circle (world axes).")
    offset: tuple[float, float, float] | None = Field(
        None, description="Centre minus start position (m); default: -radius along the plane's first axis."
    )
    ramp: float = Field(1.0, ge=0, description="Blend from the start pose onto the circle (s).")
    damping: float = Field(0.02, gt=0, description="Damped least squares λ (m).")
    gain: float = Field(20.0, ge=0, description="Task-space feedback on the commanded pose (1/s).")
    joints: list[str] | None = Field(None, description="Joints the IK may move; default: every joint.")
    model: ConfigPath | None = Field(None, description="MJCF model; default: [robot] model.")


class CircleController(Controller):
    Params = CircleParams
    params: CircleParams

    @classmethod
    def check_config(cls, params, joints, robot):
        path = params.model or robot.model
        if path is None:
            return [("params.model", "no model: set params.model or [robot] model")]
        if not os.path.exists(path):
            return [("params.model", f"file not found: {path}")]
        try:
            names = model_names(str(path))
        except ValueError as exc:
            return [("params.model", str(exc))]
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
        self._JT = np.zeros((n, m))
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

    # ------------------------------------------------------------ kinematics

    def _site_positions(self, q_all: np.ndarray, out: np.ndarray, jacobian: bool) -> None:
        """Forward kinematics at joint positions ``q_all`` (robot order) into ``out``; J if asked."""
        model, data = self.model, self.data
        data.qpos[self.all_qpos] = q_all
        mujoco.mj_kinematics(model, data)
        data.site_xpos.take(self.site_ids, axis=0, out=out.reshape(-1, 3))
        if jacobian:
            mujoco.mj_comPos(model, data)
            jac, J = self._jac_full, self.J
            for i, sid in enumerate(self.site_ids):
                mujoco.mj_jacSite(model, data, jac, None, sid)
                jac.take(self.dof_adr, axis=1, out=J[3 * i : 3 * i + 3])

    def _target(self, t: float) -> None:
        """Desired site positions and velocities at time t since start, into _x_d and _v_d."""
        p = self.params
        phase = self.omega * t
        c, s = math.cos(phase), math.sin(phase)
        x_d, v_d, tmp = self._x_d, self._v_d, self._tmp
        # x = centre + r(cos·U + sin·V),  v = rω(-sin·U + cos·V)
        np.multiply(self.U, p.radius * c, out=x_d)
        np.multiply(self.V, p.radius * s, out=tmp)
        x_d += tmp
        x_d += self.center
        np.multiply(self.U, -p.radius * self.omega * s, out=v_d)
        np.multiply(self.V, p.radius * self.omega * c, out=tmp)
        v_d += tmp
        if t < p.ramp:  # blend from the start pose: x = start + b(t)·(circle - start)
            r = t / p.ramp
            b = r * r * r * (10.0 + r * (-15.0 + 6.0 * r))
            db = 30.0 * r * r * (1.0 - r) * (1.0 - r) / p.ramp
            np.subtract(x_d, self.x_start, out=tmp)
            v_d *= b
            v_d += db * tmp
            tmp *= b
            np.add(self.x_start, tmp, out=x_d)

    # ------------------------------------------------------------ lifecycle

    def start(self, t: float) -> None:
        robot = self.robot
        self.t0 = t
        self.q_cmd = robot.state.position.copy()  # IK integrates the commanded configuration
        self._q = np.zeros(len(self.max_step)) if self._gather else self.q_cmd[self.rows]
        self.x_start = np.zeros(3 * len(self.site_ids))
        self._site_positions(self.q_cmd, self.x_start, jacobian=False)
        offset = np.array(self.params.offset) if self.params.offset is not None else -self.params.radius * self.u
        self.center = self.x_start + np.tile(offset, len(self.site_ids))
        self._last_target = self.x_start.copy()
        self.sum_sq = 0.0
        self.samples = 0
        self.max_err = 0.0
        robot.command.mode[:] = Mode.POSITION
        robot.command.velocity[:] = 0.0

    def update(self, t: float, dt: float) -> None:
        robot = self.robot
        elapsed = t - self.t0
        err = self._err
        # tracking: the measured pose against the target the last command was made for
        if elapsed > self.params.ramp:
            self._site_positions(robot.state.position, self._x, jacobian=False)
            np.subtract(self._x, self._last_target, out=err)
            err *= err
            for e in err.reshape(-1, 3).sum(axis=1):
                self.sum_sq += e
                if e > self.max_err:
                    self.max_err = e
            self.samples += len(self.site_ids)
        self._target(elapsed)
        self._site_positions(self.q_cmd, self._x, jacobian=True)
        # task velocity: feed-forward plus feedback on the commanded pose
        task = self._task
        np.subtract(self._x_d, self._x, out=task)
        task *= self.params.gain
        task += self._v_d
        # dq = Jᵀ (J Jᵀ + λ² I)⁻¹ task · dt, with MuJoCo's small dense routines: no BLAS call
        # on the tick (its first call starts a thread pool and costs milliseconds)
        J, A, w, dq = self.J, self._A, self._w, self._dq
        mujoco.mju_mulMatMatT(A, J, J)
        A += self._reg
        mujoco.mju_cholFactor(A, 0.0)
        mujoco.mju_cholSolve(w, A, task)
        mujoco.mju_mulMatTVec(dq, J, w)
        dq *= dt
        limit = self.max_step * dt
        np.minimum(dq, limit, out=dq)
        np.maximum(dq, -limit, out=dq)
        q = self._q  # q*'s moving rows (a view of q* unless they are gathered)
        if self._gather:
            self.q_cmd.take(self.rows, out=q)
        q += dq
        np.minimum(q, self.q_max, out=q)
        np.maximum(q, self.q_min, out=q)
        if self._gather:
            self.q_cmd[self.rows] = q
        cmd = robot.command
        np.copyto(cmd.position, self.q_cmd)
        if dt > 0:
            dq *= 1.0 / dt
            cmd.velocity[self.rows] = dq
        np.copyto(self._last_target, self._x_d)

    def metrics(self) -> dict:
        if not getattr(self, "samples", 0):
            return {"rms_error_m": None, "max_error_m": None, "samples": 0}
        return {
            "rms_error_m": round(math.sqrt(self.sum_sq / self.samples), 6),
            "max_error_m": round(math.sqrt(self.max_err), 6),
            "samples": self.samples,
        }
