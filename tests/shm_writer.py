"""A fast writer for the torn-read test: the door's own publisher at about 50 kHz (fifty times
a 1 kHz tick), with every value of a snapshot equal to its tick, so that a reader can tell a
torn snapshot. (Back to back, without the pause, a reader copying 64 joints would seldom
find a gap between two writes: a seqlock favours its writer.)

    python tests/shm_writer.py ROBOT DOF SECONDS     (it stops sooner when its stdin closes)
"""

from __future__ import annotations

import select
import sys
import time
import types

from aiohal.config import parse_config
from aiohal.outside.shm_door import ShmDoor
from aiohal.safety import SafetyLevel


def main(robot_name: str, dof: int, seconds: float) -> None:
    raw = {
        "robot": {"name": robot_name},
        "joints": {f"j{i}": {"velocity": 1.0} for i in range(dof)},
        "driver": [{"type": "mock", "joints": ["j*"]}],
    }
    robot = parse_config(raw).build_robot()
    control = types.SimpleNamespace(robot=robot, level=SafetyLevel.RUN, period_ns=1_000_000,
                                    estop=lambda: None, enter_hold=lambda reason: None)
    door = ShmDoor(control, 4)
    door.activate()
    print("ready", flush=True)
    state, command, fault, clock = robot.state.block, robot.command.block, robot.state.fault, robot.clock
    end = time.monotonic() + seconds
    k = 0
    mono = time.perf_counter_ns
    while True:
        for _ in range(1000):
            until = mono() + 20_000
            while mono() < until:
                pass
            k += 1
            state.fill(k)
            command.fill(k)
            fault.fill(k & 0xFFFF)
            clock.tick = k
            clock.now_ns = k
            door.publish(None)
        if time.monotonic() > end or select.select([sys.stdin], [], [], 0)[0]:
            break
    door.close()
    print(f"wrote {k}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), float(sys.argv[3]))
