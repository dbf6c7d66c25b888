"""CAN bus load from the frames a cycle carries: bits per frame with worst-case bit stuffing.

A classic data frame with an 11-bit identifier is 47 + 8·n bits (n data bytes): SOF,
identifier, RTR, IDE, r0, DLC, data, CRC and its delimiter, ACK, EOF and the intermission.
Stuffing inserts a bit after five equal ones in the 34 + 8·n bits from SOF to the CRC; in the
worst case one every four bits after the first. 29-bit identifiers add 20 bits (18 of them
stuffable). An 8-byte frame is thus 111 bits, 135 at worst; SYNC (0 bytes) 47, 55 at worst.
"""

from __future__ import annotations


def frame_bits(data_bytes: int, *, extended: bool = False, worst_case: bool = True) -> int:
    """Bits on the wire for one classic CAN data frame."""
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"a classic CAN frame carries 0..8 data bytes, not {data_bytes}")
    stuffable = 34 + 8 * data_bytes + (18 if extended else 0)
    bits = 47 + 8 * data_bytes + (20 if extended else 0)
    return bits + ((stuffable - 1) // 4 if worst_case else 0)


def load(frame_sizes: list[int], cycle_hz: float, bitrate: int, *, worst_case: bool = True) -> float:
    """The fraction of the bus (1.0 = full) that these frames take when sent at ``cycle_hz``."""
    bits = sum(frame_bits(n, worst_case=worst_case) for n in frame_sizes)
    return bits * cycle_hz / bitrate


def load_at(frames: list[tuple[int, float]], bitrate: int, *, worst_case: bool = True) -> float:
    """The same for frames each at its own rate: ``(data bytes, frames per second)`` pairs."""
    return sum(frame_bits(n, worst_case=worst_case) * hz for n, hz in frames) / bitrate
