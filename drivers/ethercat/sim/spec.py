"""The slave spec of the simulated segment: ``"drive*7,imu,ft,dio"`` -> devices in bus order."""

from __future__ import annotations

import re
from typing import Any

from .devices import Device, DigitalIO, ForceTorque, Imu
from .drive import Drive

DEVICE_CLASSES: dict[str, type[Device]] = {"drive": Drive, "imu": Imu, "ft": ForceTorque, "dio": DigitalIO}


_ITEM = re.compile(r"^(drive|imu|ft|dio)(\d*)(?:\*(\d+))?$")


def parse_spec(spec: str, seed: int = 0) -> list[Device]:
    """``"drive*7,imu,ft,dio"`` -> devices in bus order. ``dioN`` (N = 1..8) is an I/O terminal
    with N channels (``dio`` = 8, the documented one)."""
    out: list[Device] = []
    for raw in spec.split(","):
        item = raw.strip().lower()
        if not item:
            continue
        m = _ITEM.match(item)
        if not m:
            raise ValueError(f"bad slave spec item {raw!r} (expected drive, imu, ft, dio or dioN, optionally *count)")
        kind, arg, count = m.group(1), m.group(2), int(m.group(3) or 1)
        if arg and kind != "dio":
            raise ValueError(f"bad slave spec item {raw!r}: only dio takes a channel count")
        if count < 1:
            raise ValueError(f"bad slave spec item {raw!r}: count must be >= 1")
        for _ in range(count):
            pos = len(out)
            kw: dict[str, Any] = {"serial": pos + 1, "seed": seed * 1000 + pos}
            if kind == "dio" and arg:
                kw["channels"] = int(arg)
            out.append(DEVICE_CLASSES[kind](**kw))
    if not out:
        raise ValueError("empty slave spec")
    if len(out) > 200:
        raise ValueError("at most 200 slaves")
    return out
