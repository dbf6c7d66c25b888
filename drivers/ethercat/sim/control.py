"""Control commands (one JSON object each) for a running segment: fault injection and status.

Slaves are numbered from 0 in bus order (the order of the ``--slaves`` spec and of pysoem's
``master.slaves``). Codes may be given as integers or as strings such as ``"0x2310"``.

=================  ==========================================================================
``cmd``            fields
=================  ==========================================================================
``ping``           -
``status``         - (counters, per-command counts, faults, every slave's state and model)
``drop``           ``prob`` (0..1) and/or ``count`` (next N frames); ``where``: ``"before"``
                   (default: lost on the way out, no effect on the slaves) or ``"after"``
``delay``          ``ms`` (0 = off); ``count`` (next N frames, default: until cleared)
``wkc``            ``count`` (next N frames); ``delta`` (default -1); ``scope``: ``"pd"``
                   (default: frames with LRD/LWR/LRW) or ``"all"``
``break``          ``slave``: cable break in front of this slave (it and all after it vanish)
``repair``         - (undo ``break``)
``al_error``       ``slave``, ``code`` (AL status code): SAFEOP (from OP) + error flag
``drive_fault``    ``slave``, ``code`` (CiA 402 error code, e.g. 0x2310 over-current)
``hide_objects``   ``slave``, ``indices`` (list): its SDO server says these objects do not
                   exist (e.g. 0x1C12/0x1C13: its PDOs are then in its SII only)
``op_delay``       ``ms`` (0 = off); ``slave`` (default: all): SAFEOP -> OP takes that long
``device``         ``slave`` + device settings (imu: quat/gyro/acc/noise/valid; ft: wrench/
                   noise/force_limit/torque_limit; dio: pattern; drive: load/inertia/viscous/
                   coulomb/csp_hz/csv_tau/max_speed/position/fault/power_on_fault)
``dc``             ``slave`` (default: all); ``supported`` (bool): the slave's ESC has a
                   distributed clock or not (features register, DC registers; power-cycles
                   it); ``drift_ppm``: its crystal's drift; ``compensation`` (bool, false:
                   its time control loop corrects nothing)
``dc_trace``       ``since_ns`` (segment clock), ``step`` (every n-th sample), ``clear``:
                   the slaves' SYNC0 errors against the reference clock over time
``watchdog``       ``slave`` (default: all); ``divider`` (0..65535: 0x0400 at power-on,
                   default 2498 = 100 us units); ``implemented`` (false: the ESC has no SM
                   watchdog, 0x0400-0x0443 read 0 and ignore writes); ``sm_trigger``
                   (false: bit 6 of its SM control registers reads 0, the watchdog time is
                   kept but never runs); power-cycles the slaves
``eeprom_busy``    ``slave``, ``ms`` (default 50): the slave's next EEPROM read leaves its
                   EEPROM busy that long and is never done (the master's read times out)
``power_cycle``    ``slave`` (default: all): back to the power-on state (registers, SII,
                   object dictionary values, device model)
``clear``          - (drop, delay, wkc faults off; cable repaired; no EEPROM busy; every
                   slave has DC (its drift from the start, compensating) and its default SM watchdog again, no op_delay, no drive faulted at power-on, no
                   hidden objects)
``reset_counters`` -
=================  ==========================================================================

Every answer is a JSON object with ``"ok": true`` (plus data) or ``"ok": false, "error": ...``.
"""

from __future__ import annotations

import json
from typing import Any

from .drive import Drive
from .esc import WD_DIVIDER
from .segment import Segment


def _int(value: Any, name: str) -> int:
    if isinstance(value, bool):
        raise ValueError(f"{name}: expected an integer")
    if isinstance(value, int):
        return value
    if isinstance(value, str):
        return int(value, 0)
    raise ValueError(f"{name}: expected an integer, got {value!r}")


def apply(segment: Segment, command: dict[str, Any]) -> dict[str, Any]:
    """Run one command; never raises for a bad command (the error goes into the answer)."""
    try:
        return {"ok": True, **(_apply(segment, dict(command)) or {})}
    except (ValueError, KeyError, TypeError, IndexError, OverflowError, RecursionError) as exc:
        return {"ok": False, "error": f"{type(exc).__name__}: {exc}"}


def _apply(seg: Segment, c: dict[str, Any]) -> dict[str, Any] | None:
    cmd = c.pop("cmd", None)
    f = seg.faults
    if cmd == "ping":
        return {"pong": True}
    if cmd == "status":
        return seg.status()
    if cmd == "drop":
        if "prob" in c:
            p = float(c["prob"])
            if not 0.0 <= p <= 1.0:
                raise ValueError("prob must be within 0..1")
            f.drop_prob = p
        if "count" in c:
            f.drop_next = max(0, _int(c["count"], "count"))
        where = c.get("where", "before")
        if where not in ("before", "after"):
            raise ValueError("where: 'before' or 'after'")
        f.drop_after = where == "after"
        return {"faults": f.as_dict()}
    if cmd == "delay":
        ms = float(c.get("ms", 0))
        if ms < 0:
            raise ValueError("ms must be >= 0")
        f.delay_ns = int(ms * 1e6)
        f.delay_count = _int(c["count"], "count") if "count" in c else -1
        return {"faults": f.as_dict()}
    if cmd == "wkc":
        f.wkc_next = max(0, _int(c.get("count", 1), "count"))
        f.wkc_delta = _int(c.get("delta", -1), "delta")
        scope = c.get("scope", "pd")
        if scope not in ("pd", "all"):
            raise ValueError("scope: 'pd' or 'all'")
        f.wkc_all = scope == "all"
        return {"faults": f.as_dict()}
    if cmd == "break":
        seg.break_before(_int(c["slave"], "slave"))
        return {"break_at": seg.break_at}
    if cmd == "repair":
        seg.break_before(None)
        return {"break_at": None}
    if cmd == "al_error":
        seg.al_error(_int(c["slave"], "slave"), _int(c.get("code", 0x0001), "code"))
        return {"states": seg.states()}
    if cmd == "drive_fault":
        seg.drive_fault(_int(c["slave"], "slave"), _int(c.get("code", 0x2310), "code"))
        return None
    if cmd == "hide_objects":
        od = seg.slave(_int(c["slave"], "slave")).device.od
        if od is None:
            raise ValueError("this slave has no object dictionary")
        indices = c["indices"]
        if not isinstance(indices, list):
            raise ValueError("indices: expected a list")
        od.hidden = {_int(i, "indices") for i in indices}
        return None
    if cmd == "op_delay":
        ms = float(c.get("ms", 0))
        if not 0 <= ms <= 60_000:
            raise ValueError("ms must be within 0..60000")
        for esc in [seg.slave(_int(c["slave"], "slave"))] if "slave" in c else seg.slaves:
            esc.op_delay_ns = int(ms * 1e6)
        return None
    if cmd == "device":
        k = _int(c.pop("slave"), "slave")
        return {"device": seg.slave(k).device.configure(**c)}
    if cmd == "dc":
        return _dc(seg, c)
    if cmd == "dc_trace":
        answer = seg.dc_trace.as_dict(_int(c.get("since_ns", 0), "since_ns"), _int(c.get("step", 1), "step"))
        if c.get("clear", False) is True:
            seg.dc_trace.clear()
        return answer
    if cmd == "watchdog":
        targets = [_int(c["slave"], "slave")] if "slave" in c else range(len(seg.slaves))
        divider = _int(c.get("divider", WD_DIVIDER), "divider")
        if not 0 <= divider <= 0xFFFF:
            raise ValueError("divider must be within 0..65535")
        implemented, sm_trigger = c.get("implemented", True), c.get("sm_trigger", True)
        if not isinstance(implemented, bool) or not isinstance(sm_trigger, bool):
            raise ValueError("implemented, sm_trigger: expected true or false")
        for k in targets:
            esc = seg.slave(k)
            esc.wd_divider_power_on, esc.wd_implemented, esc.wd_sm_trigger = divider, implemented, sm_trigger
            seg.power_cycle(k)
        return None
    if cmd == "eeprom_busy":
        ms = float(c.get("ms", 50))
        if not 0 < ms <= 10_000:
            raise ValueError("ms must be within 0..10000")
        seg.eeprom_busy(_int(c["slave"], "slave"), ms)
        return None
    if cmd == "power_cycle":
        if "slave" in c:
            seg.power_cycle(_int(c["slave"], "slave"))
        else:
            for k in range(len(seg.slaves)):
                seg.power_cycle(k)
        return None
    if cmd == "clear":
        f.clear()
        seg.break_before(None)
        seg.eeprom_busy_off()
        for k, esc in enumerate(seg.slaves):
            esc.op_delay_ns = 0
            esc.drift_ppm, esc.dc_compensation = seg.start_drifts[k], True
            esc.dc.set_drift(seg.clock(), esc.drift_ppm)
            esc.dc.compensating = True
            if esc.device.od is not None:
                esc.device.od.hidden = set()
            if isinstance(esc.device, Drive) and esc.device.model.power_on_fault is not None:  # only drives have one
                esc.device.model.power_on_fault = None
            default_watchdog = (esc.wd_implemented, esc.wd_sm_trigger, esc.wd_divider_power_on) == (
                True,
                True,
                WD_DIVIDER,
            )
            if not esc.has_dc or not default_watchdog:
                esc.has_dc, esc.wd_implemented, esc.wd_sm_trigger, esc.wd_divider_power_on = (
                    True,
                    True,
                    True,
                    WD_DIVIDER,
                )
                seg.power_cycle(k)
        return None
    if cmd == "reset_counters":
        seg.reset_counters()
        return None
    raise ValueError(f"unknown command {cmd!r}")


def _dc(seg: Segment, c: dict[str, Any]) -> dict[str, Any]:
    """A slave's (or every slave's) distributed clock: there or not, drift, compensation."""
    targets = [_int(c["slave"], "slave")] if "slave" in c else range(len(seg.slaves))
    for key in ("supported", "compensation"):
        if key in c and not isinstance(c[key], bool):
            raise ValueError(f"{key}: expected true or false")
    if not any(key in c for key in ("supported", "drift_ppm", "compensation")):
        raise ValueError("dc: give supported, drift_ppm and/or compensation")
    drift = float(c["drift_ppm"]) if "drift_ppm" in c else None
    if drift is not None and not -1000 <= drift <= 1000:
        raise ValueError("drift_ppm must be within -1000..1000")
    for k in targets:
        esc = seg.slave(k)
        if drift is not None:
            esc.drift_ppm = drift
            esc.dc.set_drift(seg.clock(), drift)
        if "compensation" in c:
            esc.dc_compensation = esc.dc.compensating = c["compensation"]
        if "supported" in c:
            esc.has_dc = c["supported"]
            seg.power_cycle(k)
    return {"drift_ppm": [esc.drift_ppm for esc in seg.slaves]}


def apply_line(segment: Segment, line: bytes | str) -> bytes:
    """One request line (JSON) -> one answer line (JSON + newline)."""
    try:
        command = json.loads(line)
        if not isinstance(command, dict):
            raise ValueError("a JSON object is expected")
    except (ValueError, RecursionError) as exc:  # (deeply nested arrays exhaust the parser's stack)
        answer: dict[str, Any] = {"ok": False, "error": f"bad request: {type(exc).__name__}: {str(exc)[:200]}"}
    else:
        answer = apply(segment, command)
    try:
        return (json.dumps(answer) + "\n").encode()
    except (ValueError, TypeError, RecursionError):  # a command echoing back what cannot be encoded
        return (json.dumps({"ok": False, "error": "the answer could not be encoded"}) + "\n").encode()
