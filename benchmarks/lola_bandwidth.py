"""LOLA's Fig. 10 in simulation: the hip joint's closed-loop frequency response and its -3 dB
bandwidth, with and without the velocity feed-forward.

``configs/lola_hip_sim.toml`` with the ``chirp`` controller in place of the gait (a
logarithmic sweep 10-500 Hz at 0.2 mrad) on the mock driver's simulated servo drive, in
lockstep through the HAL. The loop, bus and controller run at 2 kHz: at 1 kHz the sweep's
end would sit on the Nyquist frequency. Runs:

* ``position``: position targets only (zero target velocity, so no velocity feed-forward);
* ``velocity_ff``: with the sweep's target velocity as the drives' velocity feed-forward;
* ``learned``: the same with the learned gain ``k_e`` (0.2, what ``benchmarks.lola_tracking``
  learns at 2 kHz).

The transfer function is measured position over desired position with LOLA's error
definition (``aiohal.core.tracking_error``): ``u`` the target of tick k, ``y`` the link
position measured at the same tick, estimated as Welch's H1 = S_uy / S_uu (Hann segments of
1 s, half overlapping), numpy only. Reported: the -3 dB bandwidth (the lowest frequency where
the gain falls below 1/√2, interpolated on log f), and, as LOLA's Fig. 10 draws it (100-300 Hz,
in dB), the frequency where the gain last falls through 0 dB in the band the sweep crosses.

    python -m benchmarks.lola_bandwidth [--json out.json] [--out DIR]
"""

from __future__ import annotations

import argparse
import asyncio
import math
import time
import tomllib

import numpy as np

from .common import ROOT, write_json

CONFIG = ROOT / "configs" / "lola_hip_sim.toml"
RATE_HZ = 2000.0
FIG10_BAND = (100.0, 300.0)  # LOLA's Fig. 10: 100-300 Hz, -10 to +20 dB


def transfer_function(u: np.ndarray, y: np.ndarray, fs: float, segment: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Welch's H1 estimate of Y/U: frequencies, complex gain, and coherence (0..1: how much of
    y is explained linearly by u at that frequency)."""
    if len(u) != len(y) or len(u) < segment:
        raise ValueError(f"need two signals of equal length >= {segment} samples")
    window = np.hanning(segment)
    suu = np.zeros(segment // 2 + 1)
    syy = np.zeros(segment // 2 + 1)
    suy = np.zeros(segment // 2 + 1, dtype=complex)
    for start in range(0, len(u) - segment + 1, segment // 2):
        uu, yy = u[start:start + segment], y[start:start + segment]
        spec_u = np.fft.rfft(window * (uu - uu.mean()))
        spec_y = np.fft.rfft(window * (yy - yy.mean()))
        suu += np.abs(spec_u) ** 2
        syy += np.abs(spec_y) ** 2
        suy += np.conj(spec_u) * spec_y
    with np.errstate(divide="ignore", invalid="ignore"):
        gain = suy / suu
        coherence = np.abs(suy) ** 2 / (suu * syy)
    return np.fft.rfftfreq(segment, 1.0 / fs), gain, coherence


def bandwidth_3db(f: np.ndarray, gain: np.ndarray, f_min: float, f_max: float) -> float | None:
    """The lowest frequency in [f_min, f_max] where |gain| falls below 1/√2, interpolated
    linearly in dB against log f; None when it stays above."""
    keep = (f >= f_min) & (f <= f_max)
    freq, db = f[keep], 20.0 * np.log10(np.abs(gain[keep]))
    below = np.flatnonzero(db < -3.0103)
    if len(below) == 0:
        return None
    i = below[0]
    if i == 0:
        return float(freq[0])
    x0, x1 = math.log(freq[i - 1]), math.log(freq[i])
    return float(math.exp(x0 + (x1 - x0) * (-3.0103 - db[i - 1]) / (db[i] - db[i - 1])))


def crossing_0db(f: np.ndarray, gain: np.ndarray, f_min: float, f_max: float) -> float | None:
    """The highest frequency in [f_min, f_max] where |gain| falls through 0 dB, interpolated in
    dB against log f; None when it does not cross there."""
    keep = (f >= f_min) & (f <= f_max)
    freq, db = f[keep], 20.0 * np.log10(np.abs(gain[keep]))
    down = np.flatnonzero((db[:-1] >= 0.0) & (db[1:] < 0.0))
    if len(down) == 0:
        return None
    i = down[-1]
    x0, x1 = math.log(freq[i]), math.log(freq[i + 1])
    return float(math.exp(x0 + (x1 - x0) * db[i] / (db[i] - db[i + 1])))


def chirp_config(velocity_feedforward: bool, k_e: float, chirp: dict):
    from aiohal.config import parse_config

    raw = tomllib.loads(CONFIG.read_text())
    raw["loop"] = {"rate_hz": RATE_HZ, "clock": "virtual"}
    raw["controller"] = {"type": "chirp", "params": {**chirp, "velocity_feedforward": velocity_feedforward}}
    raw["feedforward"] = {**raw.get("feedforward", {}), "k_e": k_e}
    return parse_config(raw)


async def chirp_run(velocity_feedforward: bool, k_e: float, chirp: dict) -> dict:
    """One sweep: the target sent and the position measured at every tick, and the estimate."""
    from aiohal import ControlLoop

    config = chirp_config(velocity_feedforward, k_e, chirp)
    params = config.controller.params
    # the hold after the sweep keeps its end off the last segment's tapered edge
    ticks = round((params.settle + params.duration + params.settle) * RATE_HZ)
    sent = np.zeros(ticks + 1)
    measured = np.zeros(ticks + 1)
    count = [0]

    def record(control) -> None:
        i = count[0]
        if i < len(sent):
            sent[i] = control.robot.command.position[0]  # after the limits: what the drive got
            measured[i] = control.robot.state.position[0]
            count[0] = i + 1

    loop = ControlLoop(config)
    async with loop:
        loop.add_publisher(record)
        report = await loop.run(duration=ticks / RATE_HZ)
    n = count[0]
    delay = config.feedforward.measurement_delay_ticks
    # LOLA's definition: the target of a tick against the position measured at its instant
    u, y = sent[: n - delay], measured[delay:n]
    f, gain, coherence = transfer_function(u, y, RATE_HZ, segment=round(RATE_HZ))
    # the band the sweep crosses at full amplitude, between its fade-in and its fade-out
    rate = math.log(params.f_end / params.f_start) / params.duration
    f_lo, f_hi = params.f_start * math.exp(rate * params.ramp), params.f_end * math.exp(-rate * params.ramp)
    bandwidth = bandwidth_3db(f, gain, f_lo, f_hi)
    band = (f >= f_lo) & (f <= f_hi)
    trusted = band & (coherence >= 0.5)  # as drawn (see figure)
    below = band & (f <= (bandwidth or params.f_end))
    return {"f": f[band], "gain": gain[band], "coherence": coherence[band], "bandwidth_hz": bandwidth,
            "crossing_0db_hz": crossing_0db(f, gain, f_lo, f_hi),
            "peak_db": float(20 * np.log10(np.abs(gain[trusted]).max())),
            "min_coherence_below_bandwidth": float(coherence[below].min()),
            "faults": report["faults"], "refused": report["commands_refused"]}


def figure(path, runs: dict, labels: dict) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig = plt.figure(figsize=(7, 10))
    grid = fig.add_gridspec(4, 1, height_ratios=(3, 3, 2, 1.2))
    lola = fig.add_subplot(grid[0])
    mag = fig.add_subplot(grid[1])
    pha = fig.add_subplot(grid[2], sharex=mag)
    coh = fig.add_subplot(grid[3], sharex=mag)
    for name, run in runs.items():
        bw = run["bandwidth_hz"]
        text = f"{bw:.0f} Hz" if bw is not None else "> f_end"
        # bins where the coherence is below 0.5 say more about the estimate than the joint: not drawn
        trusted = run["coherence"] >= 0.5
        gain_db = np.where(trusted, 20 * np.log10(np.abs(run["gain"])), np.nan)
        phase = np.where(trusted, np.degrees(np.unwrap(np.angle(np.where(trusted, run["gain"], 1.0)))), np.nan)
        line, = mag.semilogx(run["f"], gain_db, lw=1.0, label=f"{labels[name]}: -3 dB at {text}")
        pha.semilogx(run["f"], phase, lw=1.0, color=line.get_color())
        coh.semilogx(run["f"], run["coherence"], lw=1.0, color=line.get_color())
        if bw is not None:
            mag.axvline(bw, color=line.get_color(), ls=":", lw=0.8)
    for name, run in runs.items():  # LOLA's axes: 100-300 Hz, -10 to +20 dB, linear f
        band = (run["f"] >= FIG10_BAND[0]) & (run["f"] <= FIG10_BAND[1])
        cross = run["crossing_0db_hz"]
        lola.plot(run["f"][band], 20 * np.log10(np.abs(run["gain"][band])), lw=1.0,
                  label=f"{labels[name]}: 0 dB at {cross:.0f} Hz" if cross else labels[name])
    lola.axhline(0.0, color="0.5", lw=0.8)
    lola.set_xlim(*FIG10_BAND)
    lowest = min(float(np.min(20 * np.log10(np.abs(run["gain"][(run["f"] >= FIG10_BAND[0]) & (run["f"] <= FIG10_BAND[1])]))))
                 for run in runs.values())
    lola.set_ylim(min(-10.0, lowest - 2.0), 20)  # LOLA's -10 dB, or lower where the joint's gain is
    lola.set_xlabel("frequency (Hz)")
    lola.set_ylabel("gain (dB)")
    lola.set_title("As LOLA's Fig. 10 draws it (LOLA: 0 dB at 241 Hz)")
    lola.legend(fontsize=8)
    lola.grid(alpha=0.3)
    mag.axhline(-3.0, color="0.5", ls="--", lw=0.8)
    mag.set_ylabel("gain (dB)")
    mag.set_ylim(-40, 6)
    mag.set_title("Hip flexion, measured / commanded position (cf. LOLA Fig. 10)")
    mag.legend(fontsize=8)
    pha.set_ylabel("phase (°)")
    coh.set_ylabel("coherence")
    coh.set_ylim(0, 1.05)
    coh.set_xlabel("frequency (Hz)")
    for ax in (mag, pha, coh):
        ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return str(path)


async def main_async(args) -> dict:
    start = time.perf_counter()
    chirp = {"amplitude": args.amplitude, "f_start": args.f_start, "f_end": args.f_end, "duration": args.duration}
    runs = {"position": await chirp_run(False, 0.0, chirp),
            "velocity_ff": await chirp_run(True, 0.0, chirp),
            "learned": await chirp_run(True, args.k_e, chirp)}
    result = {
        "rate_hz": RATE_HZ,
        "chirp": chirp,
        "k_e": args.k_e,
        "bandwidth_hz": {name: run["bandwidth_hz"] for name, run in runs.items()},
        "crossing_0db_hz": {name: run["crossing_0db_hz"] for name, run in runs.items()},
        "peak_db": {name: run["peak_db"] for name, run in runs.items()},
        "min_coherence_below_bandwidth": {name: run["min_coherence_below_bandwidth"] for name, run in runs.items()},
        "faults": {name: run["faults"] for name, run in runs.items()},
        "commands_refused": {name: run["refused"] for name, run in runs.items()},
    }
    if not args.no_figures:
        from pathlib import Path

        labels = {"position": "position only", "velocity_ff": "velocity feed-forward",
                  "learned": f"velocity feed-forward, k_e = {args.k_e:g}"}
        result["figures"] = [figure(Path(args.out) / "lola_fig10_bode.png", runs, labels)]
    result["seconds"] = round(time.perf_counter() - start, 1)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", help="write the results here")
    parser.add_argument("--out", default=str(ROOT / "bench-results" / "lola"), help="folder of the PNG")
    parser.add_argument("--no-figures", action="store_true")
    parser.add_argument("--amplitude", type=float, default=0.0002, help="of the sweep (rad)")
    parser.add_argument("--f-start", type=float, default=10.0)
    parser.add_argument("--f-end", type=float, default=500.0)
    parser.add_argument("--duration", type=float, default=4.0, help="of the sweep (s)")
    parser.add_argument("--k-e", type=float, default=0.2, help="the learned gain of the third run")
    args = parser.parse_args()
    result = asyncio.run(main_async(args))
    for name, bw in result["bandwidth_hz"].items():
        text = f"{bw:.1f} Hz" if bw is not None else f"above {args.f_end:g} Hz"
        cross = result["crossing_0db_hz"][name]
        print(f"{name}: -3 dB bandwidth {text}, 0 dB crossing "
              f"{f'{cross:.1f} Hz' if cross else 'none'}, peak {result['peak_db'][name]:+.2f} dB, "
              f"coherence >= {result['min_coherence_below_bandwidth'][name]:.3f} up to it")
    print(f"{result['seconds']} s")
    for path in result.get("figures", []):
        print("figure:", path)
    write_json(args.json, result)


if __name__ == "__main__":
    main()
