"""A simulated CiA 402 servo drive (Elmo-like), whatever bus carries it.

The drive's application: its objects (0x1001 and 0x6000 up), state machine, modes, dynamics,
faults and their emergency codes. A bus simulator puts its own communication around it (the
EtherCAT slave's SII, mailbox and PDO assignment; the CANopen node's NMT, SDO server and PDO
engine): it gives the model the object dictionary to build its objects into and a function
that sends its emergencies, decodes the master's outputs into those objects, and calls
:meth:`DriveModel.step` after each exchange.

State machine (statusword 0x6041 from controlword 0x6040, CiA 402 / IEC 61800-7-201):

    Not ready to switch on -> Switch on disabled       (automatic, at start-up)
    Switch on disabled     -> Ready to switch on       shutdown      (cw & 0x87 == 0x06)
    Ready to switch on     -> Switched on              switch on     (cw & 0x8F == 0x07)
    Ready to switch on     -> Operation enabled        switch on + enable (cw & 0x8F == 0x0F)
    Switched on            -> Operation enabled        enable operation   (cw & 0x8F == 0x0F)
    Operation enabled      -> Switched on              disable operation  (cw & 0x8F == 0x07)
    Switched on / OE       -> Ready to switch on       shutdown
    any enabled state      -> Switch on disabled       disable voltage (cw & 0x82 == 0x00)
    Operation enabled      -> Quick stop active        quick stop (cw & 0x86 == 0x02)
    Quick stop active      -> Switch on disabled       after the 0x6085 ramp (0x605A = 1..4), at
                                                       once (0); 5, 6: stays until disabled
    any                    -> Fault reaction active    internal or injected fault
    Fault reaction active  -> Fault                    motor stopped (torque off)
    Fault                  -> Switch on disabled       0 -> 1 edge of controlword bit 7

Modes (0x6060, display 0x6061): 8 CSP, 9 CSV, 10 CST, taken at once when written by SDO, at
the next exchange when written through the PDO (another value written through the PDO keeps
the previous mode; with no supported mode yet, Operation enabled gives no torque).

Two dynamics, chosen per drive with ``configure(dynamics=...)``:

``"servo"``: LOLA's cascade with a motor, gear and load (:mod:`aiohal.simulation.servo`, the
model every simulated drive shares; parameters with ``configure(servo={...})``, a hip-like joint by
default). CSP runs the whole cascade on the interpolated target with 0x60B1 and 0x60B2 as its
velocity and torque feed-forward, CSV the velocity and current loops, CST the current loop;
quick stop ramps the speed target down at 0x6085; any other state turns the power stage off.
0x6072 limits the current. The drive's units are the motor's, as a real drive's: encoder
counts (0x608F) and per mille of its rated torque (0x6076), the joint behind the model's
gear (``gear_ratio``, which the master's units must match).

``"motor"`` (the default): a simple motor, integrated over the time since the previous
exchange in sub-steps of at most 1 ms:

* CSP: a second-order position loop (natural frequency ``csp_hz``, damping 1) on a setpoint
  interpolated linearly from the previous target to the new one, velocity feed-forward from
  0x60B1 where the RxPDOs map it (else from the targets' slope plus 0x60B1), torque
  feed-forward 0x60B2 (per mille of 0x6076), torque limited by 0x6072 (the EtherCAT
  slave's RxPDO 0x1602 maps both offsets);
* CSV: first-order velocity tracking (time constant ``csv_tau``), acceleration limited by the
  available torque;
* CST: torque (0x6071 + 0x60B2, per mille of 0x6076) drives an inertia with viscous and Coulomb
  friction plus an optional external load torque.

When the outputs are lost (the EtherCAT slave leaves OP, the CANopen node OPERATIONAL), the
abort connection option code 0x6007 decides: 0 nothing, 1 fault 0x8130, 2 disable voltage
(default: the drive disables), 3 quick stop.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from . import od as odm
from .od import RW, ObjectDictionary, SdoAbort

# states
NOT_READY = "not_ready_to_switch_on"
SWITCH_ON_DISABLED = "switch_on_disabled"
READY = "ready_to_switch_on"
SWITCHED_ON = "switched_on"
OPERATION_ENABLED = "operation_enabled"
QUICK_STOP = "quick_stop_active"
FAULT_REACTION = "fault_reaction_active"
FAULT = "fault"

_STATUS_BITS = {
    NOT_READY: 0x0000,
    SWITCH_ON_DISABLED: 0x0040,
    READY: 0x0021,
    SWITCHED_ON: 0x0023,
    OPERATION_ENABLED: 0x0027,
    QUICK_STOP: 0x0007,
    FAULT_REACTION: 0x000F,
    FAULT: 0x0008,
}
_VOLTAGE = {READY, SWITCHED_ON, OPERATION_ENABLED, QUICK_STOP, FAULT_REACTION}
# statusword per state: state bits, bit 4 voltage enabled, bit 9 remote
_STATUS_WORD = {st: bits | (0x0010 if st in _VOLTAGE else 0) | 0x0200 for st, bits in _STATUS_BITS.items()}

CSP, CSV, CST = 8, 9, 10
SUPPORTED_MODES = (CSP, CSV, CST)
FAULT_COMMUNICATION = 0x8130
MAX_SUBSTEP = 0.001
MAX_GAP = 0.1  # longest interval integrated at once (s); beyond it the model just holds


class DriveModel:
    """One simulated CiA 402 drive (see the module's docstring)."""

    # model parameters (SI units; settable through configure())
    inertia = 2e-5  # kg m^2 at the motor
    viscous = 5e-4  # N m s / rad
    coulomb = 2e-3  # N m
    csp_hz = 40.0
    csv_tau = 0.005  # s
    max_speed = 1000.0  # rad/s
    dynamics = "motor"  # or "servo" (see the module's docstring)
    servo_params: Any = None  # aiohal.simulation.servo.ServoParams for "servo"; None: the hip-like defaults

    def __init__(self, od: ObjectDictionary, emergency: Callable[[int, int], None]) -> None:
        """Its objects built into ``od``; ``emergency(code, register)`` sends an EMCY."""
        self.emergency = emergency
        self._build(od)
        self.power_on()

    def _build(self, od: ObjectDictionary) -> None:
        self._ff_mapped = False  # the master's outputs map the velocity offset (outputs_mapped)

        def check_mode(entry, value):
            if value not in SUPPORTED_MODES:
                raise SdoAbort(odm.ABORT_VALUE_RANGE, f"mode {value} not supported")
            self._take_mode(value)  # a mode written by SDO is taken at once, and shown in 0x6061

        self.e_error_register = od.var(0x1001, "Error register", odm.UINT8, 0, mappable="tx")
        self.e_abort_option = od.var(0x6007, "Abort connection option code", odm.INT16, 2, RW, low=0, high=3)
        self.e_error_code = od.var(0x603F, "Error code", odm.UINT16, 0, mappable="tx")
        self.e_cw = od.var(0x6040, "Controlword", odm.UINT16, 0, RW, mappable="rx")
        self.e_sw = od.var(0x6041, "Statusword", odm.UINT16, 0, mappable="tx")
        self.e_qs_option = od.var(0x605A, "Quick stop option code", odm.INT16, 2, RW, low=0, high=6)
        self.e_mode = od.var(0x6060, "Modes of operation", odm.INT8, 0, RW, mappable="rx", on_write=check_mode)
        self.e_mode_display = od.var(0x6061, "Modes of operation display", odm.INT8, 0, mappable="tx")
        self.e_pos = od.var(0x6064, "Position actual value", odm.INT32, 0, mappable="tx")
        self.e_ferr_window = od.var(0x6065, "Following error window", odm.UINT32, 100000, RW)
        self.e_vel = od.var(0x606C, "Velocity actual value", odm.INT32, 0, mappable="tx")
        self.e_target_torque = od.var(0x6071, "Target torque", odm.INT16, 0, RW, mappable="rx")
        self.e_max_torque = od.var(0x6072, "Max torque", odm.UINT16, 1000, RW, mappable="rx")
        self.e_rated_torque = od.var(0x6076, "Motor rated torque", odm.UINT32, 1000, RW, low=1)
        self.e_torque = od.var(0x6077, "Torque actual value", odm.INT16, 0, mappable="tx")
        self.e_target_pos = od.var(0x607A, "Target position", odm.INT32, 0, RW, mappable="rx")
        self.e_qs_decel = od.var(0x6085, "Quick stop deceleration", odm.UINT32, 131072 * 20, RW, low=1)
        self.e_encoder = od.record(
            0x608F,
            "Position encoder resolution",
            [
                ("Encoder increments", odm.UINT32, 131072, RW),
                ("Motor revolutions", odm.UINT32, 1, RW),
            ],
        )
        od.record(
            0x6091,
            "Gear ratio",
            [
                ("Motor revolutions", odm.UINT32, 1, RW),
                ("Shaft revolutions", odm.UINT32, 1, RW),
            ],
        )
        self.e_vel_offset = od.var(0x60B1, "Velocity offset", odm.INT32, 0, RW, mappable="rx")
        self.e_torque_offset = od.var(0x60B2, "Torque offset", odm.INT16, 0, RW, mappable="rx")
        self.e_ferr = od.var(0x60F4, "Following error actual value", odm.INT32, 0, mappable="tx")
        self.e_target_vel = od.var(0x60FF, "Target velocity", odm.INT32, 0, RW, mappable="rx")
        od.var(0x6502, "Supported drive modes", odm.UINT32, (1 << 7) | (1 << 8) | (1 << 9))
        for e in (self.e_encoder[0], self.e_encoder[1]):
            e.low = 1
        for e in (self.e_encoder[0], self.e_encoder[1], self.e_rated_torque):
            e.on_write = self._mark_params

    #: a fault the drive finds in its self-test at every power-on (e.g. 0x7500, a brake or
    #: encoder error stored from before): it comes up in Fault; set through configure()
    power_on_fault: int | None = None

    def outputs_mapped(self, entries) -> None:
        """The objects the master's outputs now carry: with the velocity offset among them it is
        the velocity feed-forward, else the drive derives one from its targets' slope."""
        self._ff_mapped = any(e is self.e_vel_offset for e in entries)

    def power_on(self) -> None:
        self.state = NOT_READY
        self.pos = 0.0  # counts
        self.vel = 0.0  # counts/s
        self.torque = 0.0  # N m
        self.load = 0.0  # external load torque, N m
        self.mode = 0
        self._last_cw = 0
        self._last_ns: int | None = None
        self._last_target: int | None = None
        self._target_slope = 0.0
        self._fault_pending: int | None = None
        self._qs_ramp = False
        self.saturated = False
        self.faults = 0
        self.outputs_lost_ns: int | None = None
        self._servo: Any = None  # aiohal.simulation.servo.ServoBank (dynamics "servo"), built where the joint stands
        self._servo_loop = -1
        self._cw_state: str | None = None  # the state the last controlword was applied in
        self._params_dirty = True
        self.e_error_code.value = 0
        self.e_error_register.value = 0
        self.e_cw.value = 0
        if self.power_on_fault is not None:
            self._fault_pending = self.power_on_fault  # entered with the first exchange (SAFEOP)
        self._publish()

    # ------------------------------------------------------------------ control interface
    def inject_fault(self, code: int) -> None:
        """An internal drive fault (e.g. 0x2310 over-current): fault reaction, then Fault."""
        self._fault_pending = code & 0xFFFF

    def _enter_fault(self, code: int) -> None:
        self.faults += 1
        self.e_error_code.value = code
        reg = 0x01
        group = code >> 12
        if group == 0x2:
            reg |= 0x02  # current
        elif group == 0x3:
            reg |= 0x04  # voltage
        elif group == 0x4:
            reg |= 0x08  # temperature
        elif group == 0x8:
            reg |= 0x10  # communication
        self.e_error_register.value = reg
        self.state = FAULT_REACTION
        self.emergency(code, reg)

    def outputs_lost(self, now_ns: int) -> None:
        option = int(self.e_abort_option.value)
        if self.state not in (READY, SWITCHED_ON, OPERATION_ENABLED, QUICK_STOP):
            return
        self.outputs_lost_ns = now_ns  # when the drive went to its safe state (0x6007)
        if option == 1:
            self._enter_fault(FAULT_COMMUNICATION)
        elif option == 2:
            self.state = SWITCH_ON_DISABLED
        elif option == 3:
            if self.state == OPERATION_ENABLED:
                self.state = QUICK_STOP
            else:
                self.state = SWITCH_ON_DISABLED
        self._publish()

    def self_test_done(self) -> None:
        """Not ready to switch on -> Switch on disabled (the bus's communication is up)."""
        if self.state == NOT_READY:
            self.state = SWITCH_ON_DISABLED
            self._publish()

    def configure(self, **kw: Any) -> dict:
        for key, value in kw.items():
            if key == "fault":
                self.inject_fault(int(value, 0) if isinstance(value, str) else int(value))
            elif key == "power_on_fault":  # null: none; applies from the next power cycle
                self.power_on_fault = (
                    None if value is None else (int(value, 0) if isinstance(value, str) else int(value)) & 0xFFFF
                )
            elif key == "load":
                self.load = float(value)
            elif key in ("inertia", "viscous", "coulomb", "csp_hz", "csv_tau", "max_speed"):
                v = float(value)
                if v <= 0 and key not in ("viscous", "coulomb"):
                    raise ValueError(f"drive: {key} must be > 0")
                setattr(self, key, v)
            elif key == "dynamics":
                if value not in ("motor", "servo"):
                    raise ValueError(f"drive: dynamics must be 'motor' or 'servo', not {value!r}")
                self.dynamics = value
                self._servo = None  # built at the next step, where the joint stands
                if value == "servo":
                    self._warm_servo()
            elif key == "servo":
                from aiohal.simulation.servo import ServoParams

                if not isinstance(value, dict):
                    raise ValueError("drive: servo must be a table of aiohal.simulation.servo.ServoParams fields")
                try:
                    self.servo_params = ServoParams(**value)
                except ValueError as exc:  # pydantic's ValidationError is one
                    raise ValueError(f"drive: servo: {exc}") from None
                self._servo = None
            elif key == "position":
                self.pos = float(value)
                self._servo = None
                self._publish()
            else:
                raise ValueError(f"drive: unknown setting {key!r}")
        return self.status()

    def status(self) -> dict:
        return {
            "state": self.state,
            "mode": self.mode,
            "dynamics": self.dynamics,
            "position": self.pos,
            "velocity": self.vel,
            "torque": self.torque,
            "velocity_offset": int(self.e_vel_offset.value),
            "torque_offset": int(self.e_torque_offset.value),
            "error_code": int(self.e_error_code.value),
            "faults": self.faults,
            "outputs_lost_ns": self.outputs_lost_ns,
        }

    # ------------------------------------------------------------------ cycle
    def _refresh_params(self) -> None:
        inc = int(self.e_encoder[0].value) or 1
        revs = int(self.e_encoder[1].value) or 1
        self._cpr = inc / revs / (2.0 * math.pi)
        self._rated_nm = int(self.e_rated_torque.value) / 1000.0
        self._params_dirty = False

    def _mark_params(self, entry, value) -> None:
        self._params_dirty = True

    def _take_mode(self, mode: int) -> None:
        self.mode = mode
        self._last_target = None
        self.e_mode_display.value = mode

    def step(self, now_ns: int, outputs_valid: bool) -> None:
        last = self._last_ns
        self._last_ns = now_ns
        dt = (now_ns - last) * 1e-9 if last is not None else 0.0
        if self._fault_pending is not None or self.state in (NOT_READY, FAULT_REACTION):
            self._pending_transitions()
        if outputs_valid:
            cw = self.e_cw.value
            if cw != self._last_cw or self.state is not self._cw_state:
                self._controlword(cw)
                self._cw_state = self.state
            mode = self.e_mode.value
            if mode != self.mode and mode in SUPPORTED_MODES:
                self._take_mode(mode)
            target = self.e_target_pos.value
            last_target = self._last_target
            if last_target is None or dt <= 0.0:
                self._target_slope = 0.0
            else:
                self._target_slope = (((target - last_target + 0x80000000) & 0xFFFFFFFF) - 0x80000000) / dt
            self._last_target = target
        else:
            self._target_slope = 0.0
            self._last_target = None
        if dt > 0.0:
            self._integrate(dt if dt < MAX_GAP else MAX_GAP)
        self._publish()

    def _pending_transitions(self) -> None:
        if self.state == NOT_READY:
            self.state = SWITCH_ON_DISABLED
        if self._fault_pending is not None:
            code, self._fault_pending = self._fault_pending, None
            if self.state not in (FAULT, FAULT_REACTION):
                self._enter_fault(code)
        elif self.state == FAULT_REACTION:
            self.state = FAULT  # the reaction (torque off) takes one cycle here

    def _controlword(self, cw: int) -> None:
        s = self.state
        edge7 = cw & 0x80 and not self._last_cw & 0x80
        self._last_cw = cw
        if s in (FAULT_REACTION, NOT_READY):
            return
        if s == FAULT:
            if edge7:
                self.state = SWITCH_ON_DISABLED
                self.e_error_code.value = 0
                self.e_error_register.value = 0
                self.emergency(0x0000, 0)
            return
        if cw & 0x80:
            return  # fault reset bit set outside Fault: no other command
        disable_voltage = not cw & 0x02
        quick_stop = (cw & 0x06) == 0x02
        shutdown = (cw & 0x07) == 0x06
        switch_on = (cw & 0x0F) == 0x07
        enable = (cw & 0x0F) == 0x0F
        if s == SWITCH_ON_DISABLED:
            if shutdown:
                self.state = READY
        elif s == READY:
            if disable_voltage or quick_stop:
                self.state = SWITCH_ON_DISABLED
            elif switch_on:
                self.state = SWITCHED_ON
            elif enable:
                self._enable()
        elif s == SWITCHED_ON:
            if disable_voltage or quick_stop:
                self.state = SWITCH_ON_DISABLED
            elif shutdown:
                self.state = READY
            elif enable:
                self._enable()
        elif s == OPERATION_ENABLED:
            if disable_voltage:
                self.state = SWITCH_ON_DISABLED
            elif quick_stop:
                self.state = QUICK_STOP
                if int(self.e_qs_option.value) == 0:
                    self.state = SWITCH_ON_DISABLED
            elif shutdown:
                self.state = READY
            elif switch_on:
                self.state = SWITCHED_ON
        elif s == QUICK_STOP:
            if disable_voltage:
                self.state = SWITCH_ON_DISABLED
            elif enable and int(self.e_qs_option.value) in (5, 6) and self.vel == 0.0:
                self._enable()

    def _enable(self) -> None:
        self.state = OPERATION_ENABLED
        self._last_target = None

    def _integrate(self, dt: float) -> None:
        if self._params_dirty:
            self._refresh_params()
        if self.dynamics == "servo":
            self._integrate_servo(dt)
            return
        state = self.state
        mode = self.mode
        enabled = state == OPERATION_ENABLED and mode in SUPPORTED_MODES
        quick = state == QUICK_STOP
        cpr = self._cpr
        load = self.load
        self.saturated = False
        if not enabled and not quick and self.vel == 0.0 and abs(load) <= self.coulomb:
            self.torque = 0.0  # idle and at rest: nothing moves
            return
        n = 1 if dt <= MAX_SUBSTEP else math.ceil(dt / MAX_SUBSTEP - 1e-9)
        h = dt / n
        J = self.inertia
        visc = self.viscous
        coul = self.coulomb
        tmax = self.e_max_torque.value * 0.001 * self._rated_nm  # 0x6072 may be in a PDO
        wmax = self.max_speed
        wn = 2.0 * math.pi * self.csp_hz
        vel_off = self.e_vel_offset.value / cpr
        target = slope = vt = tt = decel = step = 0.0
        if enabled:
            if mode == CSP:
                p_now = self.pos
                err0 = ((self.e_target_pos.value - int(p_now) + 0x80000000) & 0xFFFFFFFF) - 0x80000000
                # the i32 target unwrapped around the position; the setpoint moves linearly
                # from the previous target to this one over the interval being integrated
                step = self._target_slope * h
                target = p_now + err0 - self._target_slope * dt
                # velocity feed-forward, rad/s: the master's (0x60B1) where mapped, else the targets' slope
                slope = vel_off if self._ff_mapped else self._target_slope / cpr + vel_off
                tt = self.e_torque_offset.value / 1000.0 * self._rated_nm  # torque feed-forward, N m
            elif mode == CSV:
                vt = (self.e_target_vel.value) / cpr + vel_off
            else:
                tt = (self.e_target_torque.value + self.e_torque_offset.value) / 1000.0 * self._rated_nm
                tt = -tmax if tt < -tmax else tmax if tt > tmax else tt
        elif quick:
            decel = self.e_qs_decel.value / cpr
        w = self.vel / cpr
        pos = self.pos
        tau = 0.0
        for _ in range(n):
            friction = visc * w + (coul if w > 0.0 else -coul if w < 0.0 else 0.0)
            if enabled:
                if mode == CSP:
                    acc = wn * wn * (target - pos) / cpr + 2.0 * wn * (slope - w)
                    tau = J * acc + friction - load + tt
                    target += step
                elif mode == CSV:
                    tau = J * (vt - w) / self.csv_tau + friction - load
                else:
                    tau = tt
            elif quick:
                a = w / h
                a = decel if a > decel else -decel if a < -decel else a
                tau = -J * a + friction - load
            else:
                tau = 0.0  # no torque: the motor coasts
            if tau > tmax:
                tau = tmax
                self.saturated = True
            elif tau < -tmax:
                tau = -tmax
                self.saturated = True
            drive = tau + load
            w_new = w + (drive - friction) / J * h
            if ((w > 0.0) != (w_new > 0.0) or w == 0.0) and abs(drive) <= coul:
                w_new = 0.0  # static friction holds (no reversal through zero)
            if -1e-6 < w_new < 1e-6:
                w_new = 0.0  # below any encoder resolution: at rest
            if w_new > wmax:
                w_new = wmax
            elif w_new < -wmax:
                w_new = -wmax
            pos += 0.5 * (w + w_new) * h * cpr
            w = w_new
        self.pos = pos
        self.vel = w * cpr
        self.torque = tau
        if quick and w == 0.0 and int(self.e_qs_option.value) in (0, 1, 2, 3, 4):
            self.state = SWITCH_ON_DISABLED

    @staticmethod
    def _warm_servo() -> None:
        """Import and run the compiled cascade once now: the first call loads it (a few hundred
        ms), which inside an exchange would stall the whole segment."""
        from aiohal.simulation import servo as sv

        sv.ServoBank(sv.ServoParams(), np.zeros(1)).step(1e-3)

    def _integrate_servo(self, dt: float) -> None:
        """One exchange interval of the cascade: the loop and its targets from the mode and
        state, as a real drive takes them from its objects. The drive's units are the motor's
        (counts of its encoder, per mille of its rated torque); the cascade's targets are the
        joint's, through the model's gear."""
        from aiohal.simulation import servo as sv

        cpr = self._cpr
        if self._servo is None:
            params = self.servo_params or sv.ServoParams()
            self._servo = sv.ServoBank(params, np.array([self.pos / cpr / params.gear_ratio]))
            self._servo_limit = params.max_current
        bank = self._servo
        p, s = bank.params[0], bank.state[0]
        gear = p[sv.GEAR]
        state, mode = self.state, self.mode
        to_joint_torque = self._rated_nm / 1000.0 * gear  # per mille of the motor's rated torque
        vel_off = self.e_vel_offset.value / cpr  # motor rad/s
        target = velocity = torque = 0.0  # at the joint: rad, rad/s, N·m
        if state == OPERATION_ENABLED and mode == CSP:
            loop = sv.POSITION_LOOP
            err0 = ((self.e_target_pos.value - int(self.pos) + 0x80000000) & 0xFFFFFFFF) - 0x80000000
            target = (int(self.pos) + err0) / cpr / gear  # the target in counts, unwrapped
            velocity = (vel_off if self._ff_mapped else self._target_slope / cpr + vel_off) / gear
            torque = self.e_torque_offset.value * to_joint_torque
        elif state == OPERATION_ENABLED and mode == CSV:
            loop = sv.VELOCITY_LOOP
            velocity = (self.e_target_vel.value / cpr + vel_off) / gear
        elif state == OPERATION_ENABLED and mode == CST:
            loop = sv.CURRENT_LOOP
            torque = (self.e_target_torque.value + self.e_torque_offset.value) * to_joint_torque
        elif state == QUICK_STOP:
            loop = sv.VELOCITY_LOOP
            w = self.vel / cpr
            slower = max(0.0, abs(w) - self.e_qs_decel.value / cpr * dt) / gear
            velocity = slower if w > 0.0 else -slower
        else:
            loop = sv.OFF
        if loop == sv.POSITION_LOOP and self._servo_loop != sv.POSITION_LOOP:
            bank.restart(0, s[sv.QL_SAMPLE])  # the ramp starts where the drive measures the joint
        self._servo_loop = loop
        p[sv.IMAX] = min(self._servo_limit, self.e_max_torque.value * 0.001 * self._rated_nm / p[sv.KT])  # 0x6072
        bank.command(target, velocity, torque, loop)
        bank.set_external_torque(self.load * gear)  # the load is given at the motor
        bank.step(dt)
        self.pos = s[sv.QL_SAMPLE] * gear * cpr  # the joint position it measures, in motor counts
        self.vel = s[sv.W] * cpr
        self.torque = s[sv.CURRENT] * p[sv.KT]  # the motor's
        self.saturated = loop != sv.OFF and abs(s[sv.I_CMD]) >= p[sv.IMAX]
        if state == QUICK_STOP and abs(self.vel) < 1e-3 * cpr and int(self.e_qs_option.value) in (0, 1, 2, 3, 4):
            self.state = SWITCH_ON_DISABLED

    def _publish(self) -> None:
        state = self.state
        sw = _STATUS_WORD[state]
        mode = self.mode
        pos = ((int(self.pos) + 0x80000000) & 0xFFFFFFFF) - 0x80000000
        if state == OPERATION_ENABLED and mode in SUPPORTED_MODES:
            sw |= 0x1000  # the drive follows the command value
            if mode == CSP:
                ferr = ((self.e_target_pos.value - pos + 0x80000000) & 0xFFFFFFFF) - 0x80000000
                self.e_ferr.value = ferr
                if -100 <= ferr <= 100:
                    sw |= 0x0400
                if abs(ferr) > self.e_ferr_window.value:
                    sw |= 0x2000
            elif mode == CSV:
                if abs(self.e_target_vel.value - self.vel) <= 100:
                    sw |= 0x0400
            else:
                sw |= 0x0400
        else:
            self.e_ferr.value = 0
        if self.saturated:
            sw |= 0x0800
        self.e_sw.value = sw
        self.e_mode_display.value = mode
        self.e_pos.value = pos
        v = self.vel
        self.e_vel.value = 2147483647 if v >= 2147483647 else -2147483648 if v <= -2147483648 else int(v)
        if self._params_dirty:
            self._refresh_params()
        t = int(self.torque / (self._rated_nm or 1.0) * 1000.0)
        self.e_torque.value = 32767 if t > 32767 else -32768 if t < -32768 else t
