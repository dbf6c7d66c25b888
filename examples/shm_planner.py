"""A planner in its own process, streaming a trajectory to a running robot through shared memory.

Start a robot whose controller is ``stream`` (``[client] shm = true``), then this::

    python -m aiohal configs/mock_arm_stream.toml --duration 20
    python examples/shm_planner.py mock_arm_stream --duration 3

It attaches by the robot's name, reads where the robot is, and sends a point every ``--step``
seconds, ``--lead`` ahead of the robot's clock, each with its velocity (the stream controller
interpolates between them with cubic Hermite curves): a sinusoid about the start pose. At the
end it asks the robot to hold and prints a JSON summary. No asyncio, no aiohal loop here.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from aiohal.client import RobotClient, RobotNotRunning


def plan(robot: str, duration: float, step: float, lead: float, amplitude: float, frequency: float) -> dict:
    with RobotClient(robot, command=True) as client:
        start = client.read()
        q0 = start.position.copy()
        t0 = start.now_ns + int(lead * 1e9)
        span = np.minimum(client.position_max - q0, q0 - client.position_min)
        amp = np.minimum(amplitude, 0.5 * span)  # stay inside every joint's range
        w = 2 * math.pi * frequency
        n = int(duration / step) + 1
        sent = 0
        for k in range(n):
            t = k * step
            t_ns = t0 + int(t * 1e9)
            # keep about ``lead`` of trajectory queued: wait until the point is due to be sent
            while client.read().now_ns < t_ns - int(lead * 1e9):
                time.sleep(step / 10)
            ramp = min(1.0, t / 0.5)  # starts at rest, where the robot is
            client.send(q0 + amp * ramp * np.sin(w * t), velocity=amp * ramp * w * np.cos(w * t), t_ns=t_ns,
                        timeout_s=1.0)
            sent += 1
        # wait for the last point to be reached, then hand over to hold
        while client.read().now_ns < t0 + int((n - 1) * step * 1e9):
            time.sleep(step / 10)
        end = client.read()
        client.hold()
        return {"robot": robot, "points_sent": sent, "points_applied": client.applied, "points_refused": client.refused,
                "level": client.level.name.lower(), "final_command": end.command_position.round(6).tolist()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("robot", help="the robot's name ([robot] name)")
    p.add_argument("--duration", type=float, default=3.0, help="seconds of trajectory")
    p.add_argument("--step", type=float, default=0.01, help="seconds between points")
    p.add_argument("--lead", type=float, default=0.05, help="how far ahead of the robot's clock points are sent")
    p.add_argument("--amplitude", type=float, default=0.2, help="rad")
    p.add_argument("--frequency", type=float, default=0.5, help="Hz")
    args = p.parse_args(argv)
    try:
        summary = plan(args.robot, args.duration, args.step, args.lead, args.amplitude, args.frequency)
    except RobotNotRunning as exc:  # start the robot first: python -m aiohal configs/mock_arm_stream.toml
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
