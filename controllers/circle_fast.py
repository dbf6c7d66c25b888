"""What the ``circle`` controller type runs: :class:`~aiohal.controllers.circle.CircleController`
with its tick as one closure over preallocated arrays.

Why: every attribute lookup, method frame and temporary array costs more than its line on the
caches the physics step and the wait left cold; written plainly (``controllers/circle.py``, the
version to read and copy) the tick keeps the overhead benchmark's WALK-MAN ratio far above its
floor of 1.10 (docs/performance.md, "Why the compiled kernels are kept"). ``tests/test_circle.py``
checks that both give the same commands.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from .circle import CircleController


class FastCircleController(CircleController):
    def start(self, t: float) -> None:
        super().start(t)
        self._tick = _tick_function(self)

    def update(self, t: float, dt: float) -> None:
        self._tick(t, dt)


def _as_slice(index: np.ndarray) -> slice | np.ndarray:
    """A run of indices as a slice (a view instead of a gather), other indices as they are."""
    first = int(index[0])
    if np.array_equal(index, np.arange(first, first + len(index))):
        return slice(first, first + len(index))
    return index


def _tick_function(c: CircleController):
    """``update(t, dt)`` of a started controller."""
    p = c.params
    model, data = c.model, c.data
    qpos, site_xpos = data.qpos, data.site_xpos
    all_qpos, site_ids, dof_adr, J = _as_slice(c.all_qpos), c.site_ids, c.dof_adr, c.J
    jac = np.zeros((3, model.nv))
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

    radius, omega, ramp, gain = p.radius, c.omega, p.ramp, p.gain
    allowed_sq = p.max_error_m**2
    t0, center, x_start, U, V, reg = c.t0, c.center, c.x_start, c.U, c.V, c._damping
    m = len(x_start)
    A = np.zeros((m, m))
    w, x, err, task, x_d, v_d, tmp = (np.zeros(m) for _ in range(7))
    dq = np.zeros(J.shape[1])
    q_min, q_max, max_step, q_cmd = c.q_min, c.q_max, c.max_step, c.q_cmd
    rows = _as_slice(c.rows)
    gather = not isinstance(rows, slice)
    q = np.zeros(len(max_step)) if gather else q_cmd[rows]  # q*'s moving rows: a view unless gathered
    last_target = x_start.copy()  # the target the last command was made for
    sites = len(site_ids)
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
