"""A joint servo drive as simulated drives run it: LOLA's cascade (its Fig. 5) with the motor.

Inside the drive, for each joint::

    target q* (interpolated over the cycle) ─► P position ─► + velocity feed-forward
        ─► PI velocity (10 kHz) ─► + current feed-forward ─► PI current (20 kHz)
        ─► motor winding (R, L, back EMF) ─► torque k_t·i ─► rotor + gear ─► joint + load

The mechanics are on the motor side: rotor inertia plus the load's inertia through the gear
(J = J_m + J_l / N²); the joint's viscous and Coulomb friction and the load's gravity torque
(``gravity_torque · sin q``, a pendulum) act through the gear too. Static friction holds a
joint at rest while the drive torque is below the Coulomb level.

The position target of a cycle is reached at its end: the drive ramps linearly from the
previous target to the new one over the cycle (cyclic synchronous position with linear
interpolation), so a target sent at tick k is where the joint should be at tick k + 1.
Velocity feed-forward (rad/s at the joint) and torque feed-forward (N·m at the joint, turned
into current through the gear and k_t) are held over the cycle.

The drive runs one of four loops (:data:`POSITION_LOOP` … :data:`OFF`), as a CiA 402 drive's
mode and state choose them: the whole cascade (cyclic synchronous position); the velocity and
current loops with the velocity feed-forward as the speed target (cyclic synchronous
velocity); the current loop alone with the current feed-forward as its target (cyclic
synchronous torque); or none, the power stage off and the joint coasting against friction.
An external torque at the joint (a push, a contact) adds to the load.

Two formulations: :class:`ReferenceServo` is the model written plainly, one joint, object by
object, for reading and for tests; :func:`step_servos` is the same arithmetic flattened over
many joints and compiled with numba, for a simulated driver's tick (a cycle is 20 current
sub-steps per millisecond: as Python that is several hundred µs per joint).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types
from pydantic import Field

from aiohal.hal import Options


class ServoParams(Options):
    """A joint's drive and mechanics (SI units; motor side where said). The defaults make a
    hip-flexion-like joint: a 100:1 harmonic drive, a leg of about 1 kg·m² and 30 N·m of
    gravity torque at the horizontal, a 48 V motor of 0.1 N·m/A."""

    gear_ratio: float = Field(100.0, gt=0, description="Motor turns per joint turn.")
    rotor_inertia: float = Field(1.2e-4, gt=0, description="Rotor plus wave generator inertia (kg·m², motor side).")
    load_inertia: float = Field(1.0, ge=0, description="Link inertia about the joint (kg·m², joint side).")
    viscous: float = Field(2.0, ge=0, description="Viscous friction (N·m·s/rad, joint side).")
    coulomb: float = Field(3.0, ge=0, description="Coulomb friction (N·m, joint side).")
    gravity_torque: float = Field(30.0, ge=0, description="Load's m·g·l: gravity torque = this · sin(q) (N·m).")
    torque_constant: float = Field(0.1, gt=0, description="k_t (N·m/A), also the back-EMF constant (V·s/rad).")
    resistance: float = Field(0.4, gt=0, description="Winding resistance (Ω).")
    inductance: float = Field(5e-4, gt=0, description="Winding inductance (H).")
    max_current: float = Field(30.0, gt=0, description="Current limit (A).")
    max_voltage: float = Field(48.0, gt=0, description="Supply voltage: the current loop's output limit (V).")
    position_gain: float = Field(150.0, ge=0, description="P of the position loop (1/s, joint side).")
    velocity_gain: float = Field(2.0, ge=0, description="P of the velocity loop (A per rad/s, motor side).")
    velocity_integral_time: float = Field(0.004, gt=0, description="Integral time of the velocity loop (s).")
    current_gain: float = Field(4.7, ge=0, description="P of the current loop (V/A).")
    current_integral_time: float = Field(0.00125, gt=0, description="Integral time of the current loop (s).")
    current_rate_hz: float = Field(20_000.0, gt=0, description="Current loop rate; the mechanics step at it too.")
    velocity_every: int = Field(
        2, ge=1, description="The position and velocity loops run every n current steps (10 kHz at the defaults)."
    )
    velocity_filter_hz: float = Field(
        1000.0, gt=0, description="Low-pass (first order) of the measured motor speed the velocity loop uses."
    )


# columns of the parameter table (one row per joint), in ServoParams' order
PARAM_FIELDS = tuple(ServoParams.model_fields)
(
    GEAR,
    ROTOR_J,
    LOAD_J,
    VISCOUS,
    COULOMB,
    GRAVITY,
    KT,
    RES,
    IND,
    IMAX,
    VMAX,
    KP_POS,
    KP_VEL,
    TI_VEL,
    KP_CUR,
    TI_CUR,
    CUR_HZ,
    VEL_EVERY,
    VEL_FILTER_HZ,
) = range(len(PARAM_FIELDS))
# columns of the state table (one row per joint)
STATE_FIELDS = (
    "position",
    "velocity",
    "current",
    "velocity_integral",
    "current_integral",
    "current_command",
    "previous_target",
    "target",
    "velocity_ff",
    "current_ff",
    "phase",
    "measured_speed",
    "loop",
    "external_torque",
)
(Q, W, CURRENT, VEL_INT, CUR_INT, I_CMD, PREV_TARGET, TARGET, VEL_FF, CUR_FF, PHASE, W_MEAS, LOOP, EXT) = range(
    len(STATE_FIELDS)
)
# the loops the drive runs (the LOOP column)
POSITION_LOOP, VELOCITY_LOOP, CURRENT_LOOP, OFF = 0, 1, 2, 3


def param_table(params: list[ServoParams] | ServoParams, n: int) -> np.ndarray:
    """One row of numbers per joint, from one set of parameters or one per joint."""
    rows = params if isinstance(params, list) else [params] * n
    if len(rows) != n:
        raise ValueError(f"{n} joints, {len(rows)} parameter sets")
    return np.array([[float(getattr(p, f)) for f in PARAM_FIELDS] for p in rows])


# ---------------------------------------------------------------- the plain formulation


class PI:
    """A PI controller with its output clamped; the integral stops while the output is."""

    def __init__(self, gain: float, integral_time: float, limit: float) -> None:
        self.gain, self.integral_time, self.limit = gain, integral_time, limit
        self.integral = 0.0

    def output(self, error: float, dt: float, feedforward: float = 0.0) -> float:
        integral = self.integral + error * dt
        u = self.gain * (error + integral / self.integral_time) + feedforward
        if -self.limit <= u <= self.limit:
            self.integral = integral
            return u
        return max(-self.limit, min(self.limit, self.gain * (error + self.integral / self.integral_time) + feedforward))


class ReferenceServo:
    """One joint's drive and mechanics, written for reading (see the module's docstring)."""

    def __init__(self, p: ServoParams, position: float = 0.0) -> None:
        self.p = p
        self.dt = 1.0 / p.current_rate_hz
        self.velocity_pi = PI(p.velocity_gain, p.velocity_integral_time, p.max_current)
        self.current_pi = PI(p.current_gain, p.current_integral_time, p.max_voltage)
        self.inertia = p.rotor_inertia + p.load_inertia / p.gear_ratio**2  # at the motor
        self.motor_angle = position * p.gear_ratio
        self.motor_speed = 0.0
        self.measured_speed = 0.0  # filtered, as the velocity loop sees it
        self.current = 0.0
        self.current_command = 0.0
        self.previous_target = self.target = position
        self.velocity_ff = 0.0
        self.current_ff = 0.0
        self.phase = 0  # current steps since the velocity loop last ran
        self.loop = POSITION_LOOP
        self.external_torque = 0.0  # at the joint

    @property
    def position(self) -> float:
        return self.motor_angle / self.p.gear_ratio

    @property
    def velocity(self) -> float:
        return self.motor_speed / self.p.gear_ratio

    @property
    def torque(self) -> float:
        """The motor's torque at the joint (what a drive reports as its actual torque)."""
        return self.p.torque_constant * self.current * self.p.gear_ratio

    def command(self, target: float, velocity_ff: float, torque_ff: float, loop: int = POSITION_LOOP) -> None:
        self.target = target
        self.velocity_ff = velocity_ff
        self.current_ff = torque_ff / (self.p.gear_ratio * self.p.torque_constant)
        self.loop = loop

    def step(self, cycle: float) -> None:
        """Run the drive for one cycle of ``cycle`` seconds (the time until the next command)."""
        p = self.p
        n = max(1, round(cycle / self.dt))
        h = cycle / n
        for k in range(n):
            if self.phase == 0:
                hv = h * p.velocity_every
                self.measured_speed += (self.motor_speed - self.measured_speed) * (
                    1.0 - math.exp(-hv * 2.0 * math.pi * p.velocity_filter_hz)
                )
                if self.loop <= VELOCITY_LOOP:
                    speed = self.velocity_ff  # joint rad/s
                    if self.loop == POSITION_LOOP:
                        setpoint = self.previous_target + (self.target - self.previous_target) * k / n
                        speed += p.position_gain * (setpoint - self.position)
                    error = speed * p.gear_ratio - self.measured_speed
                    self.current_command = self.velocity_pi.output(error, hv, self.current_ff)
                else:  # no velocity loop: its integral starts again from zero
                    self.velocity_pi.integral = 0.0
                    self.current_command = max(-p.max_current, min(p.max_current, self.current_ff))
            self.phase = (self.phase + 1) % p.velocity_every
            if self.loop == OFF:  # the power stage is off: no current
                self.current = self.current_pi.integral = self.current_command = 0.0
            else:
                voltage = self.current_pi.output(self.current_command - self.current, h)
                self.winding(voltage, h)
            self.mechanics(h)
        self.previous_target = self.target  # reached: a cycle without a new command holds it

    def winding(self, voltage: float, h: float) -> None:
        """The R-L winding against the back EMF, solved exactly over ``h`` for a held voltage."""
        p = self.p
        steady = (voltage - p.torque_constant * self.motor_speed) / p.resistance
        decay = math.exp(-h * p.resistance / p.inductance)
        self.current = steady + (self.current - steady) * decay

    def mechanics(self, h: float) -> None:
        """Rotor and load, semi-implicit Euler; friction and gravity act at the joint."""
        p = self.p
        load = (p.gravity_torque * math.sin(self.position) - self.external_torque) / p.gear_ratio  # at the motor
        drive = p.torque_constant * self.current - load
        coulomb = p.coulomb / p.gear_ratio
        w = self.motor_speed
        friction = p.viscous / p.gear_ratio**2 * w + (coulomb if w > 0 else -coulomb if w < 0 else 0.0)
        w_new = w + (drive - friction) / self.inertia * h
        if (w == 0.0 or (w > 0) != (w_new > 0)) and abs(drive) <= coulomb:
            w_new = 0.0  # static friction holds
        self.motor_speed = w_new
        self.motor_angle += w_new * h


# ---------------------------------------------------------------- compiled, many joints

_F64_2D = types.Array(types.float64, 2, "A")
_RO_F64_2D = types.Array(types.float64, 2, "A", readonly=True)


@njit(types.void(_F64_2D, _RO_F64_2D, types.float64), cache=True, nogil=True)
def step_servos(state, params, cycle):
    """Every joint (a row of ``state`` and ``params``) over one cycle, as ReferenceServo."""
    for j in range(state.shape[0]):
        s = state[j]
        p = params[j]
        gear = p[GEAR]
        kt = p[KT]
        inertia = p[ROTOR_J] + p[LOAD_J] / (gear * gear)
        every = np.int64(p[VEL_EVERY])
        n = np.int64(round(cycle * p[CUR_HZ]))
        if n < 1:
            n = 1
        h = cycle / n
        hv = h * every
        decay = math.exp(-h * p[RES] / p[IND])
        smooth = 1.0 - math.exp(-hv * 2.0 * math.pi * p[VEL_FILTER_HZ])
        coulomb = p[COULOMB] / gear
        viscous = p[VISCOUS] / (gear * gear)
        imax, vmax = p[IMAX], p[VMAX]
        angle, w, i = s[Q], s[W], s[CURRENT]
        phase = np.int64(s[PHASE])
        loop = np.int64(s[LOOP])
        for k in range(n):
            if phase == 0:
                s[W_MEAS] += (w - s[W_MEAS]) * smooth
                if loop <= VELOCITY_LOOP:
                    speed = s[VEL_FF]
                    if loop == POSITION_LOOP:
                        setpoint = s[PREV_TARGET] + (s[TARGET] - s[PREV_TARGET]) * k / n
                        speed += p[KP_POS] * (setpoint - angle / gear)
                    error = speed * gear - s[W_MEAS]
                    integral = s[VEL_INT] + error * hv
                    u = p[KP_VEL] * (error + integral / p[TI_VEL]) + s[CUR_FF]
                    if -imax <= u <= imax:
                        s[VEL_INT] = integral
                    else:
                        u = p[KP_VEL] * (error + s[VEL_INT] / p[TI_VEL]) + s[CUR_FF]
                        u = -imax if u < -imax else (imax if u > imax else u)
                else:
                    s[VEL_INT] = 0.0
                    u = s[CUR_FF]
                    u = -imax if u < -imax else (imax if u > imax else u)
                s[I_CMD] = u
            phase = (phase + 1) % every
            if loop == OFF:
                i = 0.0
                s[CUR_INT] = 0.0
                s[I_CMD] = 0.0
            else:
                error = s[I_CMD] - i
                integral = s[CUR_INT] + error * h
                v = p[KP_CUR] * (error + integral / p[TI_CUR])
                if -vmax <= v <= vmax:
                    s[CUR_INT] = integral
                else:
                    v = p[KP_CUR] * (error + s[CUR_INT] / p[TI_CUR])
                    v = -vmax if v < -vmax else (vmax if v > vmax else v)
                steady = (v - kt * w) / p[RES]
                i = steady + (i - steady) * decay
            drive = kt * i - (p[GRAVITY] * math.sin(angle / gear) - s[EXT]) / gear
            friction = viscous * w + (coulomb if w > 0 else (-coulomb if w < 0 else 0.0))
            w_new = w + (drive - friction) / inertia * h
            if (w == 0.0 or (w > 0) != (w_new > 0)) and abs(drive) <= coulomb:
                w_new = 0.0
            w = w_new
            angle += w_new * h
        s[Q], s[W], s[CURRENT] = angle, w, i
        s[PHASE] = phase
        s[PREV_TARGET] = s[TARGET]


class ServoBank:
    """``n`` joints' drives for a simulated driver: commands in, one compiled call per cycle."""

    def __init__(self, params: list[ServoParams] | ServoParams, position: np.ndarray) -> None:
        position = np.asarray(position, dtype=np.float64)
        n = len(position)
        self.params = param_table(params, n)
        self.state = np.zeros((n, len(STATE_FIELDS)))
        self.state[:, Q] = position * self.params[:, GEAR]
        self.state[:, PREV_TARGET] = self.state[:, TARGET] = position
        self._gear = self.params[:, GEAR]
        self._torque_per_amp = self.params[:, KT] * self._gear

    def command(self, target, velocity_ff, torque_ff, loop=POSITION_LOOP) -> None:
        """Targets for every joint (arrays, or numbers for all): position and velocity
        feed-forward at the joint (rad, rad/s), torque feed-forward (N·m), and the loop."""
        s = self.state
        s[:, TARGET] = target
        s[:, VEL_FF] = velocity_ff
        np.divide(torque_ff, self._torque_per_amp, out=s[:, CUR_FF])
        s[:, LOOP] = loop

    def set_external_torque(self, torque) -> None:
        """A torque acting on the joints from outside (N·m at the joint), held until changed."""
        self.state[:, EXT] = torque

    def step(self, cycle: float) -> None:
        step_servos(self.state, self.params, cycle)

    def measure(self, position: np.ndarray, velocity: np.ndarray, effort: np.ndarray) -> None:
        """The joints' position, velocity and motor torque (joint side) into the given rows."""
        s = self.state
        np.divide(s[:, Q], self._gear, out=position)
        np.divide(s[:, W], self._gear, out=velocity)
        np.multiply(s[:, CURRENT], self._torque_per_amp, out=effort)
