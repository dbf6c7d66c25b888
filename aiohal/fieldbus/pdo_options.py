"""PDO mappings given in a configuration: ``'index:subindex:bits'`` entries per PDO mapping
object, checked for every bus that maps PDOs (EtherCAT CoE, CANopen)."""

from __future__ import annotations

from .busvar import encode_mapping


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
