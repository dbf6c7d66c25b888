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

The joint can have the lags a real one has, each part off by default (the rigid joint with
exact sensors): the gear's elasticity (a harmonic drive's three-segment stiffness curve and a
damping across it, the link a second inertia behind it, the gear's friction at the rotor); a
motor encoder and a link-side encoder with their counts per turn, read at the end of each
velocity-loop period and of each cycle; noise on the link-side reading; the drive's velocity
estimate (the motor encoder's difference over the period, then the low-pass) in place of the
exact speed; the position loop on the link-side encoder (a dual loop) or on the motor's; and
the latch of a DC-synchronous drive, which takes what it received at its next SYNC0. What the
drive reports is what it measured: the link-side reading, its speed estimate, its current.

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
    # the richer joint: each part off (0) by default, the rigid joint with exact sensors above
    stiffness_k1: float = Field(
        0.0, ge=0, description="Gear stiffness below stiffness_t1 (N·m/rad, joint side); 0: a rigid gear."
    )
    stiffness_k2: float = Field(0.0, ge=0, description="Gear stiffness from t1 to t2 (N·m/rad); 0: k1.")
    stiffness_k3: float = Field(0.0, ge=0, description="Gear stiffness above t2 (N·m/rad); 0: k2.")
    stiffness_t1: float = Field(0.0, ge=0, description="Torque where k1 ends (N·m); 0: k1 throughout.")
    stiffness_t2: float = Field(0.0, ge=0, description="Torque where k2 ends (N·m).")
    gear_damping: float = Field(0.0, ge=0, description="Damping across the gear's elasticity (N·m·s/rad, joint side).")
    motor_counts: float = Field(0.0, ge=0, description="Motor encoder counts per motor turn; 0: exact.")
    link_counts: float = Field(0.0, ge=0, description="Link-side encoder counts per joint turn; 0: exact.")
    link_noise: float = Field(0.0, ge=0, description="Noise of the link-side position (rad, standard deviation).")
    noise_seed: int = Field(12345, ge=1, lt=2147483647, description="Seed of the noise (reproducible runs).")
    velocity_estimate: bool = Field(
        False, description="The velocity loop sees the motor encoder's difference (filtered), not the exact speed."
    )
    link_feedback: bool = Field(
        False, description="The position loop runs on the link-side encoder (dual loop), not the motor's."
    )
    sync_latch: bool = Field(
        False,
        description="The drive takes the targets it receives at the start of the next cycle (its SYNC0), "
        "as a DC-synchronous drive does: one cycle more between a target and the joint.",
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
    K1,
    K2,
    K3,
    T1,
    T2,
    GEAR_DAMPING,
    MOTOR_COUNTS,
    LINK_COUNTS,
    LINK_NOISE,
    NOISE_SEED,
    VEL_ESTIMATE,
    LINK_FEEDBACK,
    SYNC_LATCH,
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
    "link_position",
    "link_velocity",
    "motor_sample",
    "link_sample",
    "noise_state",
    "pending_target",
    "pending_velocity_ff",
    "pending_current_ff",
)
(
    Q,  # the motor's angle (motor side)
    W,
    CURRENT,
    VEL_INT,
    CUR_INT,
    I_CMD,
    PREV_TARGET,
    TARGET,
    VEL_FF,
    CUR_FF,
    PHASE,
    W_MEAS,
    LOOP,
    EXT,
    QL,  # the link's angle (joint side): Q / gear when the gear is rigid
    WL,
    Q_SAMPLE,  # the motor encoder's last reading (motor side, quantised)
    QL_SAMPLE,  # the link's last measured position (quantised, with noise): what the drive reports
    NOISE,  # the noise generator's state
    PEND_TARGET,  # with sync_latch: what was received in the cycle before, taken at this cycle's start
    PEND_VEL_FF,
    PEND_CUR_FF,
) = range(len(STATE_FIELDS))
# the loops the drive runs (the LOOP column)
POSITION_LOOP, VELOCITY_LOOP, CURRENT_LOOP, OFF = 0, 1, 2, 3


def param_table(params: list[ServoParams] | ServoParams, n: int) -> np.ndarray:
    """One row of numbers per joint, from one set of parameters or one per joint."""
    rows = params if isinstance(params, list) else [params] * n
    if len(rows) != n:
        raise ValueError(f"{n} joints, {len(rows)} parameter sets")
    return np.array([[float(getattr(p, f)) for f in PARAM_FIELDS] for p in rows])


# ---------------------------------------------------------------- the joint's parts, shared

TWO_PI = 2.0 * math.pi
NOISE_MODULUS = 2147483647  # Park and Miller's minimal standard generator: x ← 48271·x mod (2³¹ − 1)


def gear_torque(twist: float, k1: float, k2: float, k3: float, t1: float, t2: float) -> float:
    """The torque through a harmonic drive twisted by ``twist`` (rad, joint side): the
    catalogues' three-segment curve, stiffness k1 up to the torque t1, k2 up to t2, k3 beyond."""
    a = abs(twist)
    k2 = k2 if k2 > 0.0 else k1
    k3 = k3 if k3 > 0.0 else k2
    if t1 <= 0.0 or a * k1 <= t1:
        torque = k1 * a
    else:
        a1 = t1 / k1
        a2 = a1 + max(t2 - t1, 0.0) / k2
        torque = t1 + k2 * (a - a1) if a <= a2 else max(t1, t2) + k3 * (a - a2)
    return torque if twist >= 0.0 else -torque


def quantise(angle: float, counts: float) -> float:
    """An encoder's reading of ``angle`` with ``counts`` per turn (0: exact), to the nearest count."""
    if counts <= 0.0:
        return angle
    step = TWO_PI / counts
    return math.floor(angle / step + 0.5) * step


def noise_draw(state: float) -> tuple[float, float]:
    """The generator's next state and a standard normal number (Box-Muller on two draws):
    integer arithmetic, so the plain and the compiled model draw the same numbers."""
    x1 = (np.int64(state) * 48271) % NOISE_MODULUS
    x2 = (x1 * 48271) % NOISE_MODULUS
    z = math.sqrt(-2.0 * math.log(x1 / NOISE_MODULUS)) * math.cos(TWO_PI * x2 / NOISE_MODULUS)
    return float(x2), z


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
        self.elastic = p.stiffness_k1 > 0.0 and p.load_inertia > 0.0
        # the inertia the motor moves: its own, plus the link's through the gear when rigid
        self.inertia = p.rotor_inertia + (0.0 if self.elastic else p.load_inertia / p.gear_ratio**2)
        self.motor_angle = position * p.gear_ratio
        self.motor_speed = 0.0
        self.link_angle = position
        self.link_speed = 0.0
        self.measured_speed = 0.0  # the velocity loop's filtered speed (motor side)
        self.noise_state = float(p.noise_seed)
        self.motor_sample = quantise(self.motor_angle, p.motor_counts)
        self.link_sample = self.read_link()
        self.current = 0.0
        self.current_command = 0.0
        self.previous_target = self.target = position
        self.velocity_ff = 0.0
        self.current_ff = 0.0
        self.pending = (position, 0.0, 0.0)  # received, taken at the next cycle's start (sync_latch)
        self.phase = 0  # current steps since the velocity loop last ran
        self.loop = POSITION_LOOP
        self.external_torque = 0.0  # at the joint

    @property
    def position(self) -> float:
        """The link position the drive measured last (what it reports)."""
        return self.link_sample

    @property
    def velocity(self) -> float:
        """The joint velocity the drive reports: its estimate, or the exact one without."""
        return self.measured_speed / self.p.gear_ratio if self.p.velocity_estimate else self.link_speed

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
        if p.sync_latch:
            received = (self.target, self.velocity_ff, self.current_ff)
            self.target, self.velocity_ff, self.current_ff = self.pending
            self.pending = received
        n = max(1, round(cycle / self.dt))
        h = cycle / n
        hv = h * p.velocity_every
        for k in range(n):
            if self.phase == 0:
                if self.loop <= VELOCITY_LOOP:
                    speed = self.velocity_ff  # joint rad/s
                    if self.loop == POSITION_LOOP:
                        setpoint = self.previous_target + (self.target - self.previous_target) * k / n
                        feedback = self.link_sample if p.link_feedback else self.motor_sample / p.gear_ratio
                        speed += p.position_gain * (setpoint - feedback)
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
            if self.phase == 0:
                self.read_encoders(hv)
        if self.phase != 0:  # the cycle ends between two readings: the drive reads the link for its report
            self.link_sample = self.read_link()
        self.previous_target = self.target  # reached: a cycle without a new command holds it

    def read_encoders(self, hv: float) -> None:
        """Both encoders, at the end of a velocity-loop period; the speed the loop will see:
        the motor encoder's difference over the period (or the exact speed), low-pass filtered."""
        p = self.p
        sample = quantise(self.motor_angle, p.motor_counts)
        speed = (sample - self.motor_sample) / hv if p.velocity_estimate else self.motor_speed
        self.motor_sample = sample
        self.measured_speed += (speed - self.measured_speed) * (1.0 - math.exp(-hv * TWO_PI * p.velocity_filter_hz))
        self.link_sample = self.read_link()

    def read_link(self) -> float:
        """The link-side encoder: quantised, plus the measurement's noise."""
        reading = quantise(self.link_angle, self.p.link_counts)
        if self.p.link_noise > 0.0:
            self.noise_state, z = noise_draw(self.noise_state)
            reading += self.p.link_noise * z
        return reading

    def winding(self, voltage: float, h: float) -> None:
        """The R-L winding against the back EMF, solved exactly over ``h`` for a held voltage."""
        p = self.p
        steady = (voltage - p.torque_constant * self.motor_speed) / p.resistance
        decay = math.exp(-h * p.resistance / p.inductance)
        self.current = steady + (self.current - steady) * decay

    def mechanics(self, h: float) -> None:
        """Rotor and load, semi-implicit Euler. Rigid: friction and gravity act on one inertia
        through the gear. Elastic: the gear's friction acts at the rotor, the twist of the gear
        (catalogue stiffness plus damping) carries the torque to the link, gravity acts there."""
        p = self.p
        gear = p.gear_ratio
        if self.elastic:
            twist = self.motor_angle / gear - self.link_angle
            spring = gear_torque(twist, p.stiffness_k1, p.stiffness_k2, p.stiffness_k3, p.stiffness_t1, p.stiffness_t2)
            spring += p.gear_damping * (self.motor_speed / gear - self.link_speed)
            load = spring / gear
        else:
            load = (p.gravity_torque * math.sin(self.link_angle) - self.external_torque) / gear  # at the motor
        drive = p.torque_constant * self.current - load
        coulomb = p.coulomb / gear
        w = self.motor_speed
        friction = p.viscous / gear**2 * w + (coulomb if w > 0 else -coulomb if w < 0 else 0.0)
        w_new = w + (drive - friction) / self.inertia * h
        if (w == 0.0 or (w > 0) != (w_new > 0)) and abs(drive) <= coulomb:
            w_new = 0.0  # static friction holds
        self.motor_speed = w_new
        self.motor_angle += w_new * h
        if self.elastic:
            link_torque = spring - p.gravity_torque * math.sin(self.link_angle) + self.external_torque
            self.link_speed += link_torque / p.load_inertia * h
            self.link_angle += self.link_speed * h
        else:
            self.link_speed = w_new / gear
            self.link_angle = self.motor_angle / gear


# ---------------------------------------------------------------- compiled, many joints

_F64_2D = types.Array(types.float64, 2, "A")
_RO_F64_2D = types.Array(types.float64, 2, "A", readonly=True)
_gear_torque = njit(cache=True, nogil=True)(gear_torque)
_quantise = njit(cache=True, nogil=True)(quantise)
_noise_draw = njit(cache=True, nogil=True)(noise_draw)


@njit(cache=True, nogil=True)
def _read_link(s, p):
    reading = _quantise(s[QL], p[LINK_COUNTS])
    if p[LINK_NOISE] > 0.0:
        s[NOISE], z = _noise_draw(s[NOISE])
        reading += p[LINK_NOISE] * z
    return reading


@njit(types.void(_F64_2D, _RO_F64_2D, types.float64), cache=True, nogil=True)
def step_servos(state, params, cycle):
    """Every joint (a row of ``state`` and ``params``) over one cycle, as ReferenceServo."""
    for j in range(state.shape[0]):
        s = state[j]
        p = params[j]
        gear = p[GEAR]
        kt = p[KT]
        elastic = p[K1] > 0.0 and p[LOAD_J] > 0.0
        inertia = p[ROTOR_J] if elastic else p[ROTOR_J] + p[LOAD_J] / (gear * gear)
        every = np.int64(p[VEL_EVERY])
        n = np.int64(round(cycle * p[CUR_HZ]))
        if n < 1:
            n = 1
        h = cycle / n
        hv = h * every
        decay = math.exp(-h * p[RES] / p[IND])
        smooth = 1.0 - math.exp(-hv * TWO_PI * p[VEL_FILTER_HZ])
        coulomb = p[COULOMB] / gear
        viscous = p[VISCOUS] / (gear * gear)
        imax, vmax = p[IMAX], p[VMAX]
        if p[SYNC_LATCH] != 0.0:
            s[TARGET], s[PEND_TARGET] = s[PEND_TARGET], s[TARGET]
            s[VEL_FF], s[PEND_VEL_FF] = s[PEND_VEL_FF], s[VEL_FF]
            s[CUR_FF], s[PEND_CUR_FF] = s[PEND_CUR_FF], s[CUR_FF]
        angle, w, i = s[Q], s[W], s[CURRENT]
        phase = np.int64(s[PHASE])
        loop = np.int64(s[LOOP])
        for k in range(n):
            if phase == 0:
                if loop <= VELOCITY_LOOP:
                    speed = s[VEL_FF]
                    if loop == POSITION_LOOP:
                        setpoint = s[PREV_TARGET] + (s[TARGET] - s[PREV_TARGET]) * k / n
                        feedback = s[QL_SAMPLE] if p[LINK_FEEDBACK] != 0.0 else s[Q_SAMPLE] / gear
                        speed += p[KP_POS] * (setpoint - feedback)
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
            if elastic:
                spring = _gear_torque(angle / gear - s[QL], p[K1], p[K2], p[K3], p[T1], p[T2])
                spring += p[GEAR_DAMPING] * (w / gear - s[WL])
                load = spring / gear
            else:
                load = (p[GRAVITY] * math.sin(s[QL]) - s[EXT]) / gear
            drive = kt * i - load
            friction = viscous * w + (coulomb if w > 0 else (-coulomb if w < 0 else 0.0))
            w_new = w + (drive - friction) / inertia * h
            if (w == 0.0 or (w > 0) != (w_new > 0)) and abs(drive) <= coulomb:
                w_new = 0.0
            w = w_new
            angle += w_new * h
            if elastic:
                s[WL] += (spring - p[GRAVITY] * math.sin(s[QL]) + s[EXT]) / p[LOAD_J] * h
                s[QL] += s[WL] * h
            else:
                s[WL] = w_new / gear
                s[QL] = angle / gear
            if phase == 0:  # both encoders at the end of a velocity-loop period
                sample = _quantise(angle, p[MOTOR_COUNTS])
                measured = (sample - s[Q_SAMPLE]) / hv if p[VEL_ESTIMATE] != 0.0 else w
                s[Q_SAMPLE] = sample
                s[W_MEAS] += (measured - s[W_MEAS]) * smooth
                s[QL_SAMPLE] = _read_link(s, p)
        if phase != 0:
            s[QL_SAMPLE] = _read_link(s, p)
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
        self.state[:, QL] = position
        self.state[:, NOISE] = self.params[:, NOISE_SEED]
        for j in range(n):  # the encoders' first readings, as ReferenceServo takes them
            self.state[j, Q_SAMPLE] = quantise(self.state[j, Q], self.params[j, MOTOR_COUNTS])
            self.state[j, QL_SAMPLE] = _read_link(self.state[j], self.params[j])
        self.state[:, PREV_TARGET] = self.state[:, TARGET] = self.state[:, PEND_TARGET] = position
        self._gear = self.params[:, GEAR]
        self._torque_per_amp = self.params[:, KT] * self._gear
        self._estimates = self.params[:, VEL_ESTIMATE] != 0.0

    def command(self, target, velocity_ff, torque_ff, loop=POSITION_LOOP) -> None:
        """Targets for every joint (arrays, or numbers for all): position and velocity
        feed-forward at the joint (rad, rad/s), torque feed-forward (N·m), and the loop."""
        s = self.state
        s[:, TARGET] = target
        s[:, VEL_FF] = velocity_ff
        np.divide(torque_ff, self._torque_per_amp, out=s[:, CUR_FF])
        s[:, LOOP] = loop

    def restart(self, rows, position) -> None:
        """The position loop starts again at ``position`` for ``rows``: its ramp, and a target
        received but not yet taken (sync_latch), start there without feed-forward."""
        s = self.state
        s[rows, PREV_TARGET] = s[rows, PEND_TARGET] = position
        s[rows, PEND_VEL_FF] = s[rows, PEND_CUR_FF] = 0.0

    def set_external_torque(self, torque) -> None:
        """A torque acting on the joints from outside (N·m at the joint), held until changed."""
        self.state[:, EXT] = torque

    def step(self, cycle: float) -> None:
        step_servos(self.state, self.params, cycle)

    def measure(self, position: np.ndarray, velocity: np.ndarray, effort: np.ndarray) -> None:
        """What the drives report, joint side, into the given rows: the link position they
        measured, the velocity (their estimate where they make one) and the motor torque."""
        s = self.state
        np.copyto(position, s[:, QL_SAMPLE])
        np.copyto(velocity, s[:, WL])
        np.divide(s[:, W_MEAS], self._gear, out=velocity, where=self._estimates)
        np.multiply(s[:, CURRENT], self._torque_per_amp, out=effort)
