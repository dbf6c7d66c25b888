"""``python -m aiohal.learn_feedforward CONFIG --out gains.toml``: learn the velocity
feed-forward gains k_e (:mod:`aiohal.core.feedforward`) on the configured controller's motion and
write them to a file that ``[feedforward] gains`` loads.

The configured gains, if any, are not used while learning: the policy starts from 0.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .config import load_config
from .core.feedforward import FeedforwardSection, GainLearner, LearningFeedforward, write_gains
from .core.loop import ControlLoop
from .errors import ConfigError


async def learn(
    config: Any, duration_s: float | None = None, on_tick: Callable[[ControlLoop], None] | None = None
) -> tuple[GainLearner, dict]:
    """Run ``config``'s robot and controller with the learner until it is done (or
    ``duration_s``); the learner and the run's report. ``on_tick`` is called after each tick
    (to record the run)."""
    section: FeedforwardSection = config.feedforward
    rate = config.loop.rate_hz
    learner = GainLearner(section.step, section.max_steps)
    loop = ControlLoop(config)
    async with loop:
        loop.feedforward = LearningFeedforward(
            loop.robot.command,
            loop.robot.state,
            learner,
            max(1, round(section.window_s * rate)),
            round(section.settle_s * rate),
            clock=loop.robot.clock,
            delay=section.measurement_delay_ticks,
        )
        windows = (section.max_steps + 2) * (1 + LearningFeedforward.MAX_REPEATS)  # repeats: see LearningFeedforward
        limit = duration_s or section.settle_s + section.window_s * windows

        def stop_when_learned(control: ControlLoop) -> None:
            if learner.done or control.faults:
                control.request_stop("learned" if learner.done else "fault")

        # one run: on a real clock, stopping and starting again between windows would hold the
        # drives for a moment, an error in the next window that has nothing to do with k_e
        loop.add_publisher(stop_when_learned)
        if on_tick is not None:
            loop.add_publisher(on_tick)
        report = await loop.run(duration=limit)
    return learner, report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m aiohal.learn_feedforward",
        description="Learn the velocity feed-forward gains k_e (LOLA's policy).",
    )
    parser.add_argument("config")
    parser.add_argument("--out", required=True, help="the gains file to write (TOML)")
    parser.add_argument("--clock", default=None, help="override [loop] clock (virtual: lockstep, as fast as it goes)")
    parser.add_argument("--duration", type=float, default=None, help="stop learning after this long (s)")
    args = parser.parse_args(argv)

    try:
        config = load_config(args.config)
        if args.clock:
            config = config.with_loop(clock=args.clock)
    except ConfigError as exc:
        print(exc, file=sys.stderr)
        return 2
    learner, report = asyncio.run(learn(config, args.duration))
    if report.get("faults"):
        print(f"faults while learning: {report['faults']}", file=sys.stderr)
        return 1
    if learner.best is None:
        print("no complete window: run longer", file=sys.stderr)
        return 1
    names = [j.name for j in config.joints]
    k_e = learner.best[0]
    trace = ", ".join(f"{k:.2f}: {rms:.3g}" for k, rms in learner.costs)
    write_gains(
        Path(args.out),
        {name: k_e for name in names},
        f"learned by python -m aiohal.learn_feedforward {args.config}\nRMS per window (k_e: rad): {trace}",
    )
    print(f"k_e = {k_e:g} (RMS {learner.best[1]:.3g} rad); windows: {trace}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
