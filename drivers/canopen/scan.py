"""List the CANopen nodes on a bus and print a ``[[driver]]`` config for them; nothing moves.

Every node id is asked for its device type by SDO (canopen's ``NodeScanner.search``); each
node that answers is read: device type (0x1000), identity (0x1018), its RPDO and TPDO
communication and mapping objects (0x1400/0x1600, 0x1800/0x1A00), and its NMT state from its
heartbeat if it sends one. No NMT command, no SDO write and no PDO is sent, so no drive
changes state.

    python -m aiohal.drivers.canopen.scan --interface socketcan --channel can0 [--toml]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field

import can
import canopen
from canopen.objectdictionary import ObjectDictionary

from .driver import INPUT_OBJECTS, OUTPUT_OBJECTS, REQUIRED

NMT_STATES = {0: "BOOT-UP", 4: "STOPPED", 5: "OPERATIONAL", 127: "PRE-OPERATIONAL"}
DRIVE_NAMES = {
    0x6041: "Statusword",
    0x6064: "Position actual value",
    0x606C: "Velocity actual value",
    0x6077: "Torque actual value",
    0x603F: "Error code",
    0x6040: "Controlword",
    0x607A: "Target position",
    0x60FF: "Target velocity",
    0x6071: "Target torque",
    0x6060: "Modes of operation",
    0x6061: "Modes of operation display",
}


@dataclass
class PdoInfo:
    number: int  # 1-based, as CiA 301 counts them
    cob_id: int
    enabled: bool
    transmission_type: int
    entries: list[tuple[int, int, int]]  # (index, subindex, bits)

    def describe(self) -> str:
        names = [DRIVE_NAMES.get(i, f"0x{i:04X}:{s:02X}") + f" ({b})" for i, s, b in self.entries]
        state = "" if self.enabled else " (disabled)"
        return f"0x{self.cob_id:03X} type {self.transmission_type}{state}: " + (", ".join(names) or "nothing mapped")


@dataclass
class NodeInfo:
    node_id: int
    device_type: int
    vendor_id: int
    product_code: int
    revision: int
    serial: int | None
    nmt_state: str | None
    rpdos: list[PdoInfo] = field(default_factory=list)
    tpdos: list[PdoInfo] = field(default_factory=list)

    @property
    def is_drive(self) -> bool:
        return self.device_type & 0xFFFF == 402

    def drive_mapping(self) -> tuple[list[str], list[str]]:
        """The drive variables the driver would use from this node's enabled PDOs, and the
        required ones it lacks."""
        mapped = {(i, s) for pdos in (self.rpdos, self.tpdos) for p in pdos if p.enabled for i, s, _ in p.entries}
        used = [DRIVE_NAMES[i] for i, s, _ in INPUT_OBJECTS + OUTPUT_OBJECTS if (i, s) in mapped]
        missing = [DRIVE_NAMES[i] for i in sorted(REQUIRED) if (i, 0) not in mapped]
        return used, missing


def _u(sdo, index: int, subindex: int) -> int:
    return int.from_bytes(sdo.upload(index, subindex), "little")


def _pdos(sdo, comm: int, mapping: int) -> list[PdoInfo]:
    out = []
    for k in range(512):
        try:
            cob_id = _u(sdo, comm + k, 1)
        except canopen.SdoAbortedError:
            break  # no such PDO: the node has k of them
        trans = _u(sdo, comm + k, 2)
        count = _u(sdo, mapping + k, 0)
        entries = []
        for sub in range(1, count + 1):
            value = _u(sdo, mapping + k, sub)
            entries.append((value >> 16, (value >> 8) & 0xFF, value & 0xFF))
        out.append(PdoInfo(k + 1, cob_id & 0x7FF, not cob_id & 0x80000000, trans, entries))
    return out


def scan(network: canopen.Network, *, limit: int = 127, listen_s: float = 0.3) -> list[NodeInfo]:
    """Every node that answers on this (connected) network, read by SDO."""
    states: dict[int, int] = {}

    def heartbeat(can_id: int, data: bytearray, timestamp: float) -> None:
        if data:
            states[can_id - 0x700] = data[0] & 0x7F

    for node_id in range(1, limit + 1):
        network.subscribe(0x700 + node_id, heartbeat)
    network.scanner.reset()
    network.scanner.search(limit)
    time.sleep(listen_s)
    found = []
    for node_id in sorted(set(network.scanner.nodes)):
        node = canopen.RemoteNode(node_id, ObjectDictionary())
        network.add_node(node)
        sdo = node.sdo
        try:
            device_type = _u(sdo, 0x1000, 0)
            vendor, product, revision = (_u(sdo, 0x1018, s) for s in (1, 2, 3))
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError):
            continue  # answered something, but not as a CANopen node we can read
        try:
            serial = _u(sdo, 0x1018, 4)
        except canopen.SdoAbortedError:
            serial = None
        state = states.get(node_id)
        found.append(
            NodeInfo(
                node_id,
                device_type,
                vendor,
                product,
                revision,
                serial,
                None if state is None else NMT_STATES.get(state, f"state {state}"),
                _pdos(sdo, 0x1400, 0x1600),
                _pdos(sdo, 0x1800, 0x1A00),
            )
        )
    for node_id in range(1, limit + 1):
        network.unsubscribe(0x700 + node_id, heartbeat)
    return found


def describe(nodes: list[NodeInfo]) -> str:
    lines = []
    for n in nodes:
        kind = "CiA 402 drive" if n.is_drive else f"device type 0x{n.device_type:08X}"
        lines.append(
            f"node {n.node_id}: {kind}, vendor 0x{n.vendor_id:08X}, product 0x{n.product_code:08X}, "
            f"revision 0x{n.revision:08X}"
            + (f", serial {n.serial}" if n.serial is not None else "")
            + f", NMT {n.nmt_state or 'unknown (no heartbeat heard)'}"
        )
        for kind_name, pdos in (("RPDO", n.rpdos), ("TPDO", n.tpdos)):
            for p in pdos:
                lines.append(f"  {kind_name}{p.number} {p.describe()}")
        if n.is_drive:
            used, missing = n.drive_mapping()
            lines.append(
                f"  the driver would use: {', '.join(used) or 'nothing'}"
                + (f"; missing (required): {', '.join(missing)}" if missing else "")
            )
    return "\n".join(lines)


def to_toml(nodes: list[NodeInfo], interface: str, channel: str, bitrate: int) -> str:
    """A ``[[driver]]`` for the drives found: rename the joints to the robot's, add each node's
    EDS and units (counts_per_rev, gear_ratio, rated_torque)."""
    drives = [n for n in nodes if n.is_drive]
    joints = [f"joint{n.node_id}" for n in drives]
    lines = [
        "[[driver]]",
        'type = "canopen"',
        'name = "can"',
        "joints = [" + ", ".join(f'"{j}"' for j in joints) + "]",
        "",
        "[driver.options]",
        f'interface = "{interface}"',
        f'channel = "{channel}"',
        f"bitrate = {bitrate}",
        "nodes = [",
    ]
    for n, joint in zip(drives, joints, strict=True):
        _used, missing = n.drive_mapping()
        note = f"  # missing: {', '.join(missing)}" if missing else ""
        lines.append(
            f'    {{ node_id = {n.node_id}, joint = "{joint}", vendor_id = 0x{n.vendor_id:08X}, '
            f"product_code = 0x{n.product_code:08X} }},{note}"
        )
    lines.append("]")
    for n in nodes:
        if not n.is_drive:
            lines.append(f"# node {n.node_id}: device type 0x{n.device_type:08X}, not a CiA 402 drive")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m aiohal.drivers.canopen.scan", description=__doc__.split("\n\n")[0])
    parser.add_argument("--interface", required=True, help="python-can interface (socketcan, pcan, ...)")
    parser.add_argument("--channel", required=True)
    parser.add_argument("--bitrate", type=int, default=1_000_000)
    parser.add_argument("--toml", action="store_true", help="print a [[driver]] config for the drives found")
    parser.add_argument("--listen", type=float, default=0.3, help="seconds to wait for answers and heartbeats")
    args = parser.parse_args(argv)
    try:
        bus = can.Bus(interface=args.interface, channel=args.channel, bitrate=args.bitrate)
    except Exception as exc:  # python-can raises several kinds for a bus it cannot open
        print(f"cannot open {args.interface}:{args.channel}: {exc}", file=sys.stderr)
        return 1
    network = canopen.Network(bus)
    network.NOTIFIER_CYCLE = 0.05
    network.connect()
    try:
        nodes = scan(network, listen_s=args.listen)
    finally:
        network.disconnect()
    if not nodes:
        print(f"no CANopen node answered on {args.interface}:{args.channel}", file=sys.stderr)
        return 1
    print(to_toml(nodes, args.interface, args.channel, args.bitrate) if args.toml else describe(nodes))
    return 0


if __name__ == "__main__":
    sys.exit(main())
