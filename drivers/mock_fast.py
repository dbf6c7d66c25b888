"""What the ``mock`` driver type runs: :class:`~aiohal.drivers.mock.MockDriver` with its joint
step compiled (``mock_kernels.step_joints``).

Why: the mock is what the HAL's own cost is measured with (work per tick p50 ≤ 25 µs at 1 kHz,
33 joints, ``hold``). The plain step in numpy is the version to read and copy; on the real
clock's cold caches its calls cost that floor several times over (docs/performance.md, "Why the
compiled kernels are kept"). ``tests/test_mock_driver.py`` checks that both move the joints
alike.
"""

from __future__ import annotations

import math

from aiohal.core import compiled_entry

from .mock import MockDriver


class FastMockDriver(MockDriver):
    async def open(self) -> None:
        await super().open()
        from . import mock_kernels  # numba, imported when a mock opens rather than when it is named

        # called without numba's dispatch: the arrays are checked here, once
        command, state = self.view.command, self.view.state
        self._step_args = (command.block, command.mode, self.sim)
        self._stamp_args = (state.updated_tick, state.stamp_ns)  # not written: stamp=False
        self._step_joints = compiled_entry.compiled_for(
            mock_kernels.step_joints, (*self._step_args, 0.0, False, 1.0, 0.0, False, *self._stamp_args, 0, 0)
        )

    def _step(self, dt: float) -> None:
        first_order = self.options.dynamics == "first_order"
        alpha = 1.0 - math.exp(-dt / self.options.time_constant) if first_order else 1.0
        self._step_joints(*self._step_args, dt, first_order, alpha, 1.0 / dt, False, *self._stamp_args, 0, 0)
