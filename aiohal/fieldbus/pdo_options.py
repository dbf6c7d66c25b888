"""Options shared by the buses that map PDOs to CiA 402 drives (EtherCAT CoE, CANopen):
``'index:subindex:bits'`` entries per PDO mapping object, and a drive's units."""

from __future__ import annotations

from pydantic import Field

from aiohal.hal import FiniteFloat, Options

from .busvar import encode_mapping
from .cia402 import DriveUnits


class DriveUnitOptions(Options):
    """A bus's ``drive_defaults``: each drive's own ``counts_per_rev``, ``gear_ratio`` and
    ``rated_torque`` override them."""

    counts_per_rev: FiniteFloat = Field(131072, gt=0, description="Encoder increments per motor revolution (0x608F).")
    gear_ratio: FiniteFloat = Field(1.0, gt=0, description="Motor revolutions per joint revolution.")
    rated_torque: FiniteFloat = Field(1.0, gt=0, description="Motor rated torque in N·m (0x6076 / 1000).")

    def units(
        self, counts_per_rev: float | None = None, gear_ratio: float | None = None, rated_torque: float | None = None
    ) -> DriveUnits:
        """One drive's units: its own values where given, these defaults elsewhere."""
        return DriveUnits(
            counts_per_rev or self.counts_per_rev, gear_ratio or self.gear_ratio, rated_torque or self.rated_torque
        )


def parse_pdo_entry(text: str) -> int:
    """``'0x607A:0:32'`` → the mapping entry 0x607A0020 (index, subindex, bits; 0x0000 pads)."""
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(f"{text!r}: expected 'index:subindex:bits', e.g. '0x607A:0:32'")
    try:
        index, subindex, bits = (parse_number(part) for part in parts)
    except ValueError:
        raise ValueError(f"{text!r}: index, subindex and bits must be integers (hex with 0x)") from None
    if not (0 <= index <= 0xFFFF and 0 <= subindex <= 0xFF and 1 <= bits <= 64):
        raise ValueError(f"{text!r}: index 0..0xFFFF, subindex 0..0xFF, bits 1..64")
    return encode_mapping(index, subindex, bits)


def parse_number(text: str) -> int:
    """``'0x1A01'``, ``'01'`` or ``'16'``: hex with 0x, else decimal (leading zeros allowed)."""
    text = text.strip()
    return int(text[2:], 16) if text.lower().startswith("0x") else int(text, 10)


def pdo_issues(where: str, pdos: dict[str, list[str]] | None, low: int, high: int) -> list[tuple[str, str]]:
    if pdos is None:
        return []
    issues = []
    if not pdos:
        issues.append((where, "no PDO: this would unassign them all (leave the key out to keep the slave's own)"))
    if len(pdos) > 254:
        issues.append((where, "at most 254 PDOs"))
    seen: dict[int, str] = {}
    for pdo, entries in pdos.items():
        try:
            index = parse_number(pdo)
        except ValueError:
            index = -1
        if not low <= index <= high:
            issues.append((f"{where}.{pdo}", f"not a PDO mapping index 0x{low:04X}..0x{high:04X}"))
        elif index in seen:
            issues.append((f"{where}.{pdo}", f"the same PDO as {seen[index]!r}"))
        seen.setdefault(index, pdo)
        if len(entries) > 254:
            issues.append((f"{where}.{pdo}", "at most 254 entries"))
        for k, entry in enumerate(entries):
            try:
                parse_pdo_entry(entry)
            except ValueError as exc:
                issues.append((f"{where}.{pdo}[{k}]", str(exc)))
    return issues
