"""Draw the end-effector paths of the four simulated robots running the same circle controller.

Each robot runs 6 s in lockstep (deterministic); the measured site positions are recorded
every tick and drawn in the circle's plane against the target circle.

    make figures        (or: python examples/plot_circles.py docs/img/circles.png)
"""

from __future__ import annotations

import asyncio
import math
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import mujoco
import numpy as np

from aiohal import ControlLoop, load_config
from aiohal.core.ticker import VirtualTickSource

ROOT = Path(__file__).resolve().parent.parent
ROBOTS = [("kuka_lwr_sim", "KUKA LWR-like, 7 DOF"), ("centauro_upper_sim", "CENTAURO-like, 15 DOF"),
          ("coman_sim", "COMAN-like, 29 DOF"), ("walkman_sim", "WALK-MAN-like, 33 DOF")]
AXES = {"xy": (0, 1), "yz": (1, 2), "xz": (0, 2)}


async def record(name: str, seconds: float = 6.0):
    config = load_config(ROOT / "configs" / f"{name}.toml").with_loop(clock="virtual")
    loop = ControlLoop(config, tick_source=VirtualTickSource())
    paths = []
    async with loop:
        sim = loop.slots[0].driver
        ids = [mujoco.mj_name2id(sim.model, mujoco.mjtObj.mjOBJ_SITE, s) for s in config.controller.params.sites]
        loop.add_publisher(lambda lp: paths.append(sim.data.site_xpos[ids].copy()))
        report = await loop.run(duration=seconds)
    return config.controller.params, np.array(paths), report


async def main(out: Path) -> None:
    fig, axes = plt.subplots(1, 4, figsize=(16, 4.4))
    for ax, (name, title) in zip(axes, ROBOTS, strict=True):
        params, paths, report = await record(name)
        a, b = AXES[params.plane]
        ramp = int(params.ramp * 1000)
        for i, site in enumerate(params.sites):
            p = paths[:, i]
            start = p[0]
            centre = start[[a, b]] - np.array([params.radius, 0.0])
            phi = np.linspace(0, 2 * math.pi, 200)
            ax.plot(centre[0] + params.radius * np.cos(phi), centre[1] + params.radius * np.sin(phi),
                    color="0.75", lw=4, label="target" if i == 0 else None)
            ax.plot(p[:ramp, a], p[:ramp, b], color="tab:red", lw=1, label="ramp in" if i == 0 else None)
            ax.plot(p[ramp:, a], p[ramp:, b], lw=1.2, color=("tab:blue", "tab:green")[i % 2], label=f"{site} (measured)")
        err = report["controller"]
        ax.set_title(f"{title}\nRMS {err['rms_error_m'] * 1e3:.2f} mm, max {err['max_error_m'] * 1e3:.2f} mm", fontsize=10)
        ax.set_xlabel(f"{'xyz'[a]} (m)")
        ax.set_ylabel(f"{'xyz'[b]} (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend(fontsize=7, loc="lower left")
    fig.suptitle("One circle controller, four robots (MuJoCo, lockstep, 1 kHz): end-effector paths", fontsize=11)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    print(f"wrote {out}")


if __name__ == "__main__":
    asyncio.run(main(Path(sys.argv[1] if len(sys.argv) > 1 else ROOT / "docs" / "img" / "circles.png")))
