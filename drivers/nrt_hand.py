"""``nrt_hand``: a hand whose driver runs outside the fast loop, behind an ``aiohal.pipe``.

As in XBot (an RT arm with a non-RT hand over XDDP), the hand's own slow loop with its
blocking I/O runs in a subprocess (default: its own interpreter and GIL) or a thread, in
``aiohal.drivers.hands.service``. In the tick this driver only reads the newest state from the
pipe and sends the grasp command when it changed, never blocking.

The hand's state ages on the fast side: older than ``stale_after_ms`` sets ``Fault.STALE`` on
the device; older than ``dead_after_ms``, or the NRT side's process or thread gone, sets
``Fault.HARDWARE`` and reports the fault once. The run goes on: the arm is not held for its
hand. A faulted hand recovers by itself when fresh state comes back (a stall that ends).
``estop`` commands nothing new: a gripper keeps its grasp, it does not drop what it holds.
"""

from __future__ import annotations

import asyncio
import math
import time
from typing import Any, Literal, cast

from pydantic import Field

from aiohal.hal import Driver, Options
from aiohal.pipe import NrtPeer
from aiohal.robot import Fault, Mode

from .hands.base import FAULT_NONE, describe_fault
from .hands.messages import HandCommandMsg, HandStateMsg

SERVICE = "aiohal.drivers.hands.service:serve"


class NrtHandOptions(Options):
    backend: str = Field("sim", description='Hand backend: "sim", "robotiq" or "package.module:Class".')
    backend_options: dict[str, Any] = Field(default_factory=dict, description="Keyword arguments of the backend.")
    mode: Literal["subprocess", "thread"] = Field(
        "subprocess", description="Where the hand's loop runs: a subprocess has its own GIL."
    )
    rate_hz: float = Field(100.0, gt=0, le=1000, description="Rate of the hand's own (NRT) loop.")
    stale_after_ms: float = Field(100.0, gt=0, description="State older than this: device STALE.")
    dead_after_ms: float = Field(500.0, gt=0, description="State older than this: device faulted.")
    start_timeout_s: float = Field(5.0, gt=0, description="open() fails if no state arrives within this.")
    resend_ms: float = Field(100.0, gt=0, description="Repeat the last command this often (a restarted hand gets it).")
    stall_after_s: float | None = Field(None, gt=0, description="Tests: the hand stops answering after this time.")


class NrtHandDriver(Driver):
    Options = NrtHandOptions
    device_kinds = frozenset({"hand"})
    options: NrtHandOptions
    #: its joint, if it has one, reads the hand's opening; the hand follows the grasp command
    #: of its device record, so the joint takes position commands (hold's, a move's) and no other
    command_modes = frozenset({Mode.POSITION})

    @classmethod
    def check_config(cls, options, joints, devices, robot):
        issues = []
        if len(devices) != 1:
            issues.append(("devices", f"nrt_hand serves exactly one hand device (got {len(devices)})"))
        if len(joints) > 1:
            issues.append(("joints", f"nrt_hand owns at most one joint, the hand's (got {', '.join(joints)})"))
        if options.dead_after_ms < options.stale_after_ms:
            issues.append(("options.dead_after_ms", "must not be shorter than stale_after_ms"))
        return issues

    def __init__(self, name, view, options) -> None:
        super().__init__(name, view, options)
        self.peer: NrtPeer | None = None  # the hand's side, once open() started it
        self.state_msg: HandStateMsg | None = None
        self.lost_reason = ""
        self.was_lost = ""  # the last loss, kept after the hand came back: the report says so
        self.faults_seen: list[int] = []  # every fault code the hand reported, in order

    async def open(self) -> None:
        opts = self.options
        (self.hand,) = self.view.devices.values()
        self._stale_ns = int(opts.stale_after_ms * 1e6)
        self._dead_ns = int(opts.dead_after_ms * 1e6)
        self._resend_ns = int(opts.resend_ms * 1e6)
        target_options = {
            "backend": opts.backend,
            "backend_options": opts.backend_options,
            "rate_hz": opts.rate_hz,
            "stall_after_s": opts.stall_after_s,
        }
        self.peer = await asyncio.to_thread(NrtPeer.start, SERVICE, target_options, mode=opts.mode)
        self.pipe = self.peer.fast
        self._sent: tuple[float, float, float] | None = None
        self._sent_ns = 0
        self._reported_code = FAULT_NONE
        deadline = time.monotonic() + opts.start_timeout_s
        while self.state_msg is None:  # bounded: start_timeout_s, polling off the tick
            self._take_state()
            if self.state_msg is not None:
                break
            if not self.peer.alive() or time.monotonic() > deadline:
                reason = self._peer_gone_reason() or f"no state within {opts.start_timeout_s:g} s"
                await asyncio.to_thread(self.peer.stop, 1.0)
                raise ConnectionError(f"hand {self.hand.name} did not start: {reason}")
            await asyncio.sleep(0.005)

    def _take_state(self) -> bool:
        """Copy the newest state from the pipe into the hand record, if one came."""
        msg = self.pipe.receive_latest()
        if not isinstance(msg, HandStateMsg):
            return False
        self.state_msg = msg
        hand = self.hand
        hand.position[...] = msg.position
        hand.effort[...] = msg.effort
        hand.object_detected[...] = msg.object_detected
        return True

    def _peer_gone_reason(self) -> str:
        peer = cast(NrtPeer, self.peer)  # called only once open() has started the peer
        if peer.alive() and self.pipe.peer_alive:
            return ""
        if peer.error:
            return f"hand {peer.mode} failed: {peer.error}"
        if peer.exitcode is not None:
            return f"hand {peer.mode} exited (code {peer.exitcode})"
        return f"hand {peer.mode} closed its end of the pipe"

    async def read(self) -> None:
        view, hand = self.view, self.hand
        clock = view.clock
        if self._take_state():
            hand.mark_fresh(clock.tick, clock.now_ns)
            if self.lost_reason:  # fresh state again: a stall is over
                self.was_lost, self.lost_reason = self.lost_reason, ""
            # _take_state() returned True: it has just set state_msg (never None here)
            code = self.state_msg.fault  # type: ignore[union-attr]
            if code != self._reported_code:
                self._reported_code = code
                if code != FAULT_NONE:
                    if code not in self.faults_seen:
                        self.faults_seen.append(code)
                    view.fault(
                        f"hand {hand.name} reports fault code {describe_fault(code, self.options.backend)}", hold=False
                    )
            bits = Fault.HARDWARE if code != FAULT_NONE else 0
        else:
            bits = self._age_fault(time.monotonic_ns())
        hand.set_fault(bits)
        if view.dof:
            state = view.state
            state.position[0] = hand.position
            state.effort[0] = hand.effort
        view.mark_fresh()  # the pipe answered without blocking; the hand's age is its own

    def _age_fault(self, now_ns: int) -> int:
        """Fault bits when no new state came this tick: stale, then lost (reported once).
        Ages are wall-clock (``time.monotonic_ns``, as the pipe stamps them), whatever the loop's clock."""
        age = now_ns - self.pipe.last_receive_ns
        gone = "" if self.pipe.peer_alive else self._peer_gone_reason() or "hand closed the pipe"
        if gone or age > self._dead_ns:
            if not self.lost_reason:
                self.lost_reason = gone or f"no state from the hand for {age / 1e6:.0f} ms"
                self.view.fault(f"hand {self.hand.name}: {self.lost_reason}", hold=False)
            return Fault.HARDWARE | Fault.STALE
        return self.hand.fault | Fault.STALE if age > self._stale_ns else self.hand.fault

    async def write(self) -> None:
        hand = self.hand
        command = (float(hand.grasp), float(hand.speed), float(hand.force))
        if not all(map(math.isfinite, command)):
            return  # keep the last command: never send NaN to a hand
        now = time.monotonic_ns()  # the hand lives in real time, also under a virtual clock
        if command != self._sent or now - self._sent_ns >= self._resend_ns:  # noqa: SIM102 - send() has an effect
            if self.pipe.send(HandCommandMsg(grasp=command[0], speed=command[1], force=command[2])):
                self._sent, self._sent_ns = command, now

    async def close(self) -> None:
        if self.peer is not None:
            await asyncio.to_thread(self.peer.stop, 1.0)

    def _hand_summary(self) -> str:
        """ "ok" only for a hand that never faulted nor went silent during the run."""
        said = []
        if self.lost_reason:
            said.append(f"lost: {self.lost_reason}")
        elif self.was_lost:
            said.append(f"was lost ({self.was_lost}), then answered again")
        if self.faults_seen:
            said.append("faulted: " + ", ".join(describe_fault(c, self.options.backend) for c in self.faults_seen))
        return "; ".join(said) or "ok"

    def health(self) -> dict:
        peer = self.peer
        if peer is None:
            return {}
        msg = self.state_msg
        return {
            "mode": peer.mode,
            "pid": peer.pid,
            "alive": peer.alive(),
            "exitcode": peer.exitcode,
            "hand": self._hand_summary(),
            "hand_fault_code": None if msg is None else msg.fault,
            "pipe": dict(self.pipe.counters),
        }
