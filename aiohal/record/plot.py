"""``aiohal plot run.mcap -o DIR``: PNG figures of a recording (extra ``plot``, matplotlib).

joints.png: each selected joint's measured position against its target, with the tracking
error; timing.png: lateness over time and its histogram, each phase's work; safety.png: the
safety level over time with the faults marked, on the same time axis as the others.
"""

from __future__ import annotations

import argparse
import fnmatch
import io
import sys
from pathlib import Path

import numpy as np

from ..core.tick_timing import PHASES
from ..files import check_output_path, write_atomically
from ..safety import SafetyLevel

#: the files ``plot`` writes in its folder
FIGURES = ("joints.png", "timing.png", "safety.png")


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        raise SystemExit("aiohal plot needs matplotlib: pip install 'aiohal[plot]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot(recording, out_dir: Path, joints: list[str] | None = None) -> list[Path]:
    """Write the figures of ``recording`` (an :class:`aiohal.record.Recording`) to ``out_dir``."""
    plt = _pyplot()
    check_out_dir(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    names = recording.joint_names
    pick = [i for i, n in enumerate(names) if not joints or any(fnmatch.fnmatchcase(n, p) for p in joints)]
    if "/joint_states" in recording and "/joint_commands" in recording and pick:
        state, command = recording["/joint_states"], recording["/joint_commands"]
        _common, si, ci = np.intersect1d(state.tick, command.tick, return_indices=True)
        t = state.t[si]
        fig, (ax, err) = plt.subplots(2, 1, sharex=True, figsize=(10, 6))
        for i in pick[:12]:
            (line,) = ax.plot(t, state.position[si, i], label=names[i], linewidth=1.5, alpha=0.6)
            # the target on top, thin and dashed, so that it shows where it lies on the position
            ax.plot(t, command.position[ci, i], "--", color=line.get_color(), linewidth=0.9, zorder=3)
            err.plot(t, (command.position[ci, i] - state.position[si, i]) * 1e3, color=line.get_color())
        ax.set_ylabel("position (solid), target (dashed)\n(rad; m for a prismatic joint)", fontsize="small")
        err.set_ylabel("target − position\n(mrad; mm for a prismatic joint)", fontsize="small")
        err.set_xlabel("time (s)")
        ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside, not over, the curves
        ax.set_title(f"{recording.info.get('robot', '')}: joints")
        written.append(_save(fig, out_dir / "joints.png", plt))
    if "/timing" in recording and len(recording["/timing"]):
        timing = recording["/timing"]
        fig, axes = plt.subplots(3, 1, figsize=(10, 8))
        axes[0].plot(timing.t, timing.lateness_ns / 1e3, linewidth=0.5)
        axes[0].set_ylabel("lateness (µs)")
        axes[0].set_xlabel("time (s)")
        axes[1].hist(timing.lateness_ns / 1e3, bins=100, log=True)
        axes[1].set_xlabel("lateness (µs)")
        axes[1].set_ylabel("ticks")
        top = 0.0
        for p in PHASES:
            work_us = timing[f"{p}_ns"] / 1e3
            axes[2].plot(timing.t, work_us, linewidth=0.5, label=p)
            top = max(top, float(np.percentile(work_us, 99.5)))
        # a few spikes would squash every phase flat: the axis ends above their 99.5th
        # percentile (the spikes are in the lateness plot and the run's report)
        axes[2].set_ylim(0, top * 1.5 or 1.0)
        axes[2].set_ylabel("phase work (µs)\n(to 1.5 × p99.5)", fontsize="small")
        axes[2].set_xlabel("time (s)")
        axes[2].legend(fontsize="small", ncol=len(PHASES))
        written.append(_save(fig, out_dir / "timing.png", plt))
    if "/safety" in recording and len(recording["/safety"]):
        safety = recording["/safety"]
        fig, ax = plt.subplots(figsize=(10, 3))
        ax.step(safety.t, safety.level, where="post")
        ax.set_yticks(range(len(SafetyLevel)), [level.name.lower() for level in sorted(SafetyLevel)])
        rate = recording.info.get("rate_hz") or 1000.0
        for fault in recording.faults:
            t = (fault["tick"] - safety.tick[0]) / rate + safety.t[0]
            ax.axvline(t, color="red", linewidth=0.8)
            ax.annotate(f"{fault['source']}", (t, 0.2), color="red", fontsize="small", rotation=90)
        ax.set_xlabel("time (s)")
        ax.set_title("safety level and faults")
        written.append(_save(fig, out_dir / "safety.png", plt))
    return written


def _save(fig, path: Path, plt) -> Path:
    fig.tight_layout()
    image = io.BytesIO()
    fig.savefig(image, dpi=100, format="png")
    plt.close(fig)
    write_atomically(path, image.getvalue())
    return path


def check_out_dir(out_dir: Path) -> None:
    """The figures' folder: a folder (or a name free for one) in which each figure's name is free
    or a regular file; ValueError says why not, before anything is drawn."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"-o {out_dir}: not a folder (the figures are {', '.join(FIGURES)} in it)")
    if out_dir.is_dir():
        for name in FIGURES:
            check_output_path(out_dir / name)


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="python -m aiohal plot", description="Plot a recording (MCAP) as PNGs.")
    p.add_argument("recording", type=Path)
    p.add_argument("-o", "--out", type=Path, default=Path("."), help="folder for the PNGs")
    p.add_argument("--joints", nargs="+", default=None, help="joint names or glob patterns (default: all, first 12)")
    args = p.parse_args(argv)
    from .reader import load

    try:
        check_out_dir(args.out)
        recording = load(args.recording)
        written = plot(recording, args.out, args.joints)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for path in written:
        print(path)
    return 0
