"""The ``sine`` controller's tick, compiled with numba.

Why compiled: ``sine`` drives the main job (``make run``: the mock humanoid, 33 joints). As
numpy its tick was a dozen calls (tracking error, its sum and maximum, the angles, their sine
and cosine, the position and velocity commands), and on the real clock each tick starts on
cold caches, where every numpy call costs several times what it costs back to back; one
compiled call pays that once. The arithmetic is the numpy version's, term for term and in the
same order (``tests/test_controllers.py`` compares them); only ``sin`` and ``cos`` may differ
from numpy's in the last bit. The command rows are literals (numba's on-disk cache freezes
module globals), checked against ``aiohal.robot`` at import.
"""

from __future__ import annotations

import math

from numba import njit, types

from aiohal.robot import JOINT_COMMAND_FIELDS

POSITION, VELOCITY = 0, 1  # rows of the command block

if JOINT_COMMAND_FIELDS[:2] != ("position", "velocity"):
    raise ImportError("controllers/sine_kernels.py: its literal command rows no longer match aiohal.robot")

_RO_ROW = types.Array(types.float64, 1, "A", readonly=True)
_ROW = types.Array(types.float64, 1, "A")
_BLOCK = types.Array(types.float64, 2, "A")


@njit(types.void(_RO_ROW, _BLOCK, _RO_ROW, _RO_ROW, _RO_ROW, _RO_ROW, _RO_ROW, types.float64, types.float64, _ROW),
      cache=True, nogil=True)
def sine_tick(measured, command, q0, amplitude, omega, phase, sin_phase, elapsed, ramp, error):
    """One tick of ``sine`` at ``elapsed`` seconds after its start.

    First the tracking error, the measured position against the position commanded the tick
    before: its squares add to ``error[0]``, its largest magnitude raises ``error[1]``, the
    joints counted add to ``error[2]``. Then the command: ``q0 + r·A·(sin(ωt+φ) − sin φ)``
    and its derivative, where ``r`` ramps the amplitude in from 0 to 1 over ``ramp`` seconds
    (minimum jerk) and is 1 after it."""
    n = measured.shape[0]
    sum_sq = 0.0
    largest = error[1]
    for j in range(n):
        e = measured[j] - command[POSITION, j]
        sum_sq += e * e
        if abs(e) > largest:
            largest = abs(e)
    error[0] += sum_sq
    error[1] = largest
    error[2] += n

    ramping = elapsed < ramp
    r = dr = 0.0
    if ramping:
        x = elapsed / ramp
        r = x * x * x * (10.0 + x * (-15.0 + 6.0 * x))
        dr = 30.0 * x * x * (1.0 - x) * (1.0 - x) / ramp
    for j in range(n):
        angle = omega[j] * elapsed + phase[j]
        s = math.sin(angle) - sin_phase[j]
        c = math.cos(angle)
        a = amplitude[j]
        if ramping:
            swing = s * a
            command[VELOCITY, j] = c * (a * omega[j] * r) + swing * dr
            command[POSITION, j] = swing * r + q0[j]
        else:
            command[POSITION, j] = s * a + q0[j]
            command[VELOCITY, j] = c * (a * omega[j])
