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
        self.qpos_adr, self.dof_adr = joint_addresses(self.model, names)
        self.all_qpos, _ = joint_addresses(self.model, list(robot.joint_names))
        self.site_ids = np.array(
            [mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, s) for s in params.sites], dtype=np.intp
        )
        m = 3 * len(self.site_ids)
        self.J = np.zeros((m, len(names)))
        self._jac = np.zeros((3, self.model.nv))
        self._damping = params.damping**2 * np.eye(m)
        self.q_min = robot.position_min[self.rows]
        self.q_max = robot.position_max[self.rows]
        self.max_step = robot.velocity_limit[self.rows] * 0.95
        a, b = PLANES[params.plane]
        self.u = np.eye(3)[a]
        self.U = np.tile(np.eye(3)[a], len(self.site_ids))  # the plane's axes, once per site
        self.V = np.tile(np.eye(3)[b], len(self.site_ids))
        self.omega = 2.0 * math.pi / params.period

    # ------------------------------------------------------------ lifecycle

    def start(self, t: float) -> None:
        robot = self.robot
        params = self.params
        self.t0 = t
        self.q_cmd = robot.state.position.copy()  # IK integrates the commanded configuration
        self.x_start = self._site_positions(self.q_cmd)
        self._jacobian()  # for _check_start
        sites = len(self.site_ids)
        if params.center is not None:
            center = np.array(params.center, dtype=float)
            self.center = np.tile(center, sites) if center.ndim == 1 else center.ravel()
        else:
            offset = np.array(params.offset) if params.offset is not None else -params.radius * self.u
            self.center = self.x_start + np.tile(offset, sites)
        self.start_warning = _check_start(self)  # raises if a circle is out of reach
        if self.start_warning:
            log.warning("circle: %s", self.start_warning)
        self.last_target = self.x_start.copy()  # the target the last command was made for
        self._error = [0.0, 0.0, 0]  # tracking: sum of squares, largest square, samples
        robot.command.mode[:] = Mode.POSITION
        robot.command.velocity[:] = 0.0

    def update(self, t: float, dt: float) -> None:
        p = self.params
        elapsed = t - self.t0
        if elapsed > p.ramp:
            self._track(p.max_error_m)
        x_d, v_d = self._target(elapsed)
        x = self._site_positions(self.q_cmd)
        J = self._jacobian()
        task = v_d + p.gain * (x_d - x)  # feed-forward plus feedback on the commanded pose
        dq = J.T @ np.linalg.solve(J @ J.T + self._damping, task) * dt
        limit = self.max_step * dt
        dq = np.clip(dq, -limit, limit)
        self.q_cmd[self.rows] = np.clip(self.q_cmd[self.rows] + dq, self.q_min, self.q_max)
        command = self.robot.command
        command.position[:] = self.q_cmd
        if dt > 0:
            command.velocity[self.rows] = dq / dt
        self.last_target = x_d

    def _target(self, elapsed: float) -> tuple[np.ndarray, np.ndarray]:
        """The sites' target position and velocity: on the circle, blended in from the start
        pose with a minimum-jerk ramp."""
        p = self.params
        phase = self.omega * elapsed
        c, s = math.cos(phase), math.sin(phase)
        x_d = self.center + p.radius * (c * self.U + s * self.V)
        v_d = p.radius * self.omega * (c * self.V - s * self.U)
        if elapsed < p.ramp:  # x = start + b(t)·(circle - start)
            r = elapsed / p.ramp
            b = r**3 * (10.0 - 15.0 * r + 6.0 * r**2)
            db = 30.0 * r**2 * (1.0 - r) ** 2 / p.ramp
            v_d = b * v_d + db * (x_d - self.x_start)
            x_d = self.x_start + b * (x_d - self.x_start)
        return x_d, v_d

    def _track(self, max_error_m: float) -> None:
        """The measured pose against the target the last command was made for; a fault above
        ``max_error_m``."""
        x = self._site_positions(self.robot.state.position)
        squares = ((x - self.last_target) ** 2).reshape(-1, 3).sum(axis=1)
        error = self._error
        error[0] += float(squares.sum())
        error[1] = max(error[1], float(squares.max()))
        error[2] += len(squares)
        if error[1] > max_error_m**2:
            raise RuntimeError(f"tracking error {math.sqrt(error[1]):.3f} m exceeds max_error_m {max_error_m:g} m")

    def _site_positions(self, q_all: np.ndarray) -> np.ndarray:
        """Forward kinematics at joint positions ``q_all`` (robot order)."""
        self.data.qpos[self.all_qpos] = q_all
        mujoco.mj_kinematics(self.model, self.data)
        return self.data.site_xpos[self.site_ids].ravel()

    def _jacobian(self) -> np.ndarray:
        """The sites' Jacobians in the last pose given to _site_positions, stacked (3 rows per site)."""
        mujoco.mj_comPos(self.model, self.data)
        for i, sid in enumerate(self.site_ids):
            mujoco.mj_jacSite(self.model, self.data, self._jac, None, int(sid))
            self.J[3 * i : 3 * i + 3] = self._jac[:, self.dof_adr]
        return self.J

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
