"""Why aiohal ticks on an absolute timerfd: five ways to tick at 1 and 2 kHz on asyncio and uvloop,
each in a fresh process, one after another, compared by the same statistics.

(a) naive ``await asyncio.sleep(period)`` (deadline k = its iteration count, so its drift shows;
it runs for the same S seconds of wall time as the others); (b) ``await asyncio.sleep(deadline -
now)`` to integer-ns deadlines t0 + k·period; (c) a thread with ``time.sleep`` to those deadlines
(no event loop: once per rate); (d) aiohal's ``ControlLoop``: mock 33-joint humanoid, ``hold``
controller; (e) aiohal's timerfd ``Ticker`` alone, doing nothing: the floor; (f) the same with
``idle_wait=False``, every wait round the event loop (what (e) does on uvloop): beside (e) on
asyncio, its CPU % is what ``ticker.IdleWait`` saves; (g) (d) with ``[loop] idle_wait = false``.

Lateness = ``time.monotonic_ns()`` right after the wake minus the ideal deadline. Workers write raw
samples and the parent computes every statistic; for (d) the samples are the loop's own stats
buffer (``stats.lateness[:count]``), its rate, missed ticks and CPU % come from its ``report()``.
"missed" is what a method can know itself: skipped timerfd expirations (d, e), ticks started a
period or more late (b, c catch up); (a) has no deadlines to miss. No real-time settings by
default (the config's ``[realtime]`` is dropped; aiohal's built-in timer slack of 1 ns remains);
``--realtime`` gives every method SCHED_FIFO 80 + mlockall, as the humanoid config does.

    python -m benchmarks.tick [--seconds 10] [--rates 1000 2000] [--loops asyncio uvloop]
                              [--methods M ...] [--realtime] [--json PATH] [--plot PNG]
"""

from __future__ import annotations

import argparse
import asyncio
import ctypes
import ctypes.util
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
from pathlib import Path

import numpy as np

from .common import ROOT, table, write_json

METHODS = ["naive", "abs_sleep", "thread", "aiohal", "ticker", "ticker_loop", "aiohal_loop"]
LABELS = {
    "naive": "(a) naive sleep(period)",
    "abs_sleep": "(b) abs-deadline sleep",
    "thread": "(c) thread + time.sleep",
    "aiohal": "(d) aiohal ControlLoop, humanoid+hold",
    "ticker": "(e) aiohal Ticker alone (floor)",
    "ticker_loop": "(f) Ticker, every wait round the loop",
    "aiohal_loop": "(g) ControlLoop, idle_wait = false",
}
FIFO_PRIORITY = 80
SAFETY_S = 1.0  # a deadline method that has not run its N ticks this long after the last deadline stops


# ---------------------------------------------------------------- worker side: one measurement


def _cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _go_realtime() -> list[str]:
    """SCHED_FIFO 80 for the calling thread and mlockall for the process; failures become notes."""
    notes = []
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        if libc.mlockall(3) != 0:  # MCL_CURRENT | MCL_FUTURE
            notes.append(f"mlockall: {os.strerror(ctypes.get_errno())}")
    except OSError as exc:
        notes.append(f"mlockall: {exc}")
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY))
    except (OSError, AttributeError) as exc:
        notes.append(f"SCHED_FIFO: {exc}")
    return notes


class Samples:
    """Preallocated lateness samples (np.full touches every page before timing starts)."""

    def __init__(self, n: int) -> None:
        self.lateness = np.full(n, 0, dtype=np.int64)
        self.count = 0
        self.t0_ns = 0
        self.last_wake_ns = 0
        self.cpu0 = self.wall0 = 0.0
        self.meta: dict = {}

    def begin(self, t0_ns: int) -> None:
        self.t0_ns = t0_ns
        self.cpu0, self.wall0 = _cpu_s(), time.monotonic()

    def end(self) -> None:
        wall = time.monotonic() - self.wall0
        elapsed = (self.last_wake_ns - self.t0_ns) / 1e9
        self.meta.setdefault("cpu_percent", round(100 * (_cpu_s() - self.cpu0) / wall, 2) if wall > 0 else None)
        self.meta.setdefault("rate_hz", round(self.count / elapsed, 3) if elapsed > 0 else None)

    def save(self, prefix: str) -> None:
        np.save(prefix + ".npy", self.lateness[: self.count])
        Path(prefix + ".json").write_text(json.dumps(self.meta))


async def naive_sleep(n: int, period_ns: int, s: Samples) -> None:
    period_s, mono, lat = period_ns / 1e9, time.monotonic_ns, s.lateness
    t0 = mono()
    s.begin(t0)
    t_end = t0 + n * period_ns  # same wall time as the others: its lost ticks show as rate and drift
    k = 0
    while k < n:
        await asyncio.sleep(period_s)
        woke = mono()
        k += 1
        lat[k - 1] = woke - (t0 + k * period_ns)
        s.last_wake_ns = woke
        if woke >= t_end:
            break
    s.count = k
    s.meta["missed"] = None


async def abs_deadline_sleep(n: int, period_ns: int, s: Samples) -> None:
    mono, lat = time.monotonic_ns, s.lateness
    t0 = mono()
    s.begin(t0)
    limit = t0 + n * period_ns + int(SAFETY_S * 1e9)
    late = k = 0
    woke = t0
    while k < n and woke < limit:
        k += 1
        deadline = t0 + k * period_ns
        await asyncio.sleep(max(0, deadline - mono()) / 1e9)
        woke = mono()
        lat[k - 1] = woke - deadline
        if woke - deadline >= period_ns:
            late += 1
    s.count, s.last_wake_ns = k, woke
    s.meta["missed"] = late


def thread_sleep(n: int, period_ns: int, s: Samples, realtime: bool) -> None:
    def body() -> None:
        if realtime:
            s.meta["realtime_notes"] = _go_realtime()  # SCHED_FIFO is per thread: set it in the tick thread
        mono, sleep, lat = time.monotonic_ns, time.sleep, s.lateness
        t0 = mono()
        s.begin(t0)
        limit = t0 + n * period_ns + int(SAFETY_S * 1e9)
        late = k = 0
        woke = t0
        while k < n and woke < limit:
            k += 1
            deadline = t0 + k * period_ns
            wait = deadline - mono()
            if wait > 0:
                sleep(wait / 1e9)
            woke = mono()
            lat[k - 1] = woke - deadline
            if woke - deadline >= period_ns:
                late += 1
        s.count, s.last_wake_ns = k, woke
        s.meta["missed"] = late
        s.end()

    t = threading.Thread(target=body, name="tick")
    t.start()
    t.join()


async def bare_ticker(n: int, period_ns: int, s: Samples, idle_wait: bool = True) -> None:
    from aiohal.core.ticker import Ticker, TimerfdTickSource

    mono, lat = time.monotonic_ns, s.lateness
    ticker = Ticker(TimerfdTickSource(idle_wait=idle_wait), period_ns)
    ticker.start(lead_ns=period_ns)
    s.begin(ticker.t0_ns)
    limit = ticker.t0_ns + n * period_ns + int(SAFETY_S * 1e9)
    i = 0
    woke = mono()
    try:
        while ticker.k < n and woke < limit:
            await ticker.next()
            woke = mono()
            lat[i] = woke - ticker.deadline_ns
            i += 1
    finally:
        ticker.close()
    s.count, s.last_wake_ns = i, woke
    s.meta["missed"] = ticker.missed
    s.meta["waits"] = {"on_timer": ticker.source.idle_waits, "through_loop": ticker.source.loop_waits}


def humanoid_config(rate: float, n: int, realtime: bool, idle_wait: bool = True):
    """configs/mock_humanoid.toml with the hold controller, at ``rate``, [realtime] kept or dropped."""
    from aiohal import parse_config

    path = ROOT / "configs" / "mock_humanoid.toml"
    raw = tomllib.loads(path.read_text())
    raw["controller"] = {"type": "hold"}
    raw.setdefault("loop", {})["rate_hz"] = rate
    raw["loop"]["idle_wait"] = idle_wait
    raw["loop"]["stats_window"] = max(1 << 17, n + 1024)  # keep every tick: no ring wrap
    if not realtime:
        raw.pop("realtime", None)
    return parse_config(raw, base_dir=path.parent, path=path)


async def aiohal_loop(n: int, period_ns: int, s: Samples, realtime: bool, idle_wait: bool = True) -> None:
    from aiohal import ControlLoop

    config = humanoid_config(1e9 / period_ns, n, realtime, idle_wait)
    async with ControlLoop(config) as robot:
        report = await robot.run(ticks=n)
    count = robot.stats.count
    s.lateness[: min(count, n)] = robot.stats.lateness[: min(count, n)]
    s.count = min(count, n)
    s.meta.update({
        "missed": report["missed_ticks"],
        "rate_hz": report["rate_hz_achieved"],
        "cpu_percent": report["cpu_percent"],
        "report": {key: report[key] for key in ("lateness_us", "work_us", "drift_us", "realtime", "faults", "ticks", "waits")},
    })


def run_worker(method: str, rate: float, loop_name: str, seconds: float, out: str, realtime: bool) -> None:
    period_ns = round(1e9 / rate)
    n = round(seconds * rate)
    s = Samples(n)
    if method == "thread":
        thread_sleep(n, period_ns, s, realtime)
    else:
        if realtime and not method.startswith("aiohal"):  # aiohal applies its config's [realtime] itself
            s.meta["realtime_notes"] = _go_realtime()
        coro = {
            "naive": lambda: naive_sleep(n, period_ns, s),
            "abs_sleep": lambda: abs_deadline_sleep(n, period_ns, s),
            "ticker": lambda: bare_ticker(n, period_ns, s),
            "ticker_loop": lambda: bare_ticker(n, period_ns, s, idle_wait=False),
            "aiohal": lambda: aiohal_loop(n, period_ns, s, realtime),
            "aiohal_loop": lambda: aiohal_loop(n, period_ns, s, realtime, idle_wait=False),
        }[method]
        if loop_name == "uvloop":
            import uvloop

            factory = uvloop.new_event_loop
        else:
            factory = asyncio.new_event_loop
        with asyncio.Runner(loop_factory=factory) as runner:
            runner.run(coro())
        s.end()
    s.save(out)


# ---------------------------------------------------------------- parent side: run, summarise, show


def run_one(method: str, rate: float, loop_name: str, seconds: float, realtime: bool, tmp: str) -> tuple[np.ndarray, dict]:
    prefix = os.path.join(tmp, f"{method}-{rate:g}-{loop_name}")
    cmd = [sys.executable, "-m", "benchmarks.tick", "--worker", method, f"{rate:g}", loop_name,
           "--seconds", str(seconds), "--out", prefix] + (["--realtime"] if realtime else [])
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=3 * seconds + 60)
    if proc.returncode != 0 or not os.path.exists(prefix + ".npy"):
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return np.load(prefix + ".npy"), json.loads(Path(prefix + ".json").read_text())


def summarise(lat_ns: np.ndarray, period_ns: int) -> dict:
    """Every method's statistics, computed the same way from its raw lateness samples (µs)."""
    us = lat_ns / 1e3
    if us.size == 0:
        return {"ticks": 0}
    p50, p99, p999 = np.percentile(us, (50, 99, 99.9))
    m = min(100, us.size)
    return {
        "ticks": int(us.size),
        "p50": float(p50), "p99": float(p99), "p999": float(p999), "max": float(us.max()), "min": float(us.min()),
        "drift": float(np.median(us[-m:]) - np.median(us[:m])),
        "last": float(us[-1]),
        "late_1_period": int((lat_ns >= period_ns).sum()),
    }


def fmt_us(v: float | None) -> str:
    """µs, switching to ms where the naive loop's drift makes µs unreadable."""
    if v is None:
        return "–"
    return f"{v / 1e3:.1f} ms" if abs(v) >= 10_000 else f"{v:.1f}"


def plot_cdf(samples: dict[str, np.ndarray], rate: float, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.6), dpi=120)
    styles = {"naive": ("tab:red", "-"), "abs_sleep": ("tab:orange", "-"), "aiohal": ("tab:blue", "-"),
              "ticker": ("0.4", "--")}
    for method, lat in samples.items():
        us = np.sort(np.maximum(lat / 1e3, 1.0))  # log axis: ≤ 1 µs (early wakes) drawn at 1 µs
        frac_later = 1.0 - np.arange(us.size) / us.size
        color, ls = styles[method]
        p50 = float(np.median(lat)) / 1e3
        p50_text = f"{p50 / 1e3:.0f} ms" if p50 >= 10_000 else f"{p50:.0f} µs"
        ax.step(us, frac_later, where="post", color=color, ls=ls, lw=1.6, label=f"{LABELS[method]}: p50 {p50_text}")
    for q, name in ((0.5, "p50"), (0.01, "p99"), (0.001, "p99.9")):
        ax.axhline(q, color="0.8", lw=0.8, zorder=0)
        ax.text(1.05, q * 1.08, name, color="0.5", fontsize=8)
    period_us = 1e6 / rate
    ax.axvline(period_us, color="0.6", lw=0.8, ls=":", zorder=0)
    ax.text(period_us * 1.06, 0.6, "1 period", color="0.5", fontsize=8, rotation=90, va="top")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(1, None)
    ax.set_ylim(min(1e-4, 0.5 / max(len(v) for v in samples.values())), 1.2)
    ax.set_xlabel("lateness after the deadline (µs, log)")
    ax.set_ylabel("fraction of ticks later than x (log)")
    ax.set_title(f"Tick lateness at {rate:g} Hz on asyncio, one process each")
    ax.grid(True, which="major", color="0.92")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, fontsize=8, frameon=False)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--rates", type=float, nargs="+", default=[1000.0, 2000.0])
    p.add_argument("--loops", nargs="+", choices=("asyncio", "uvloop"), default=["asyncio", "uvloop"])
    p.add_argument("--methods", nargs="+", choices=METHODS, default=METHODS)
    p.add_argument("--realtime", action="store_true", help="SCHED_FIFO 80 + mlockall for every method")
    p.add_argument("--json", default=None)
    p.add_argument("--plot", default=None, metavar="PNG", help="lateness distributions at 1 kHz (or the first rate), asyncio")
    p.add_argument("--worker", nargs=3, metavar=("METHOD", "RATE", "LOOP"), help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        method, rate, loop_name = args.worker
        run_worker(method, float(rate), loop_name, args.seconds, args.out, args.realtime)
        return

    plot_rate = 1000.0 if 1000.0 in args.rates else args.rates[0]
    plot_samples: dict[str, np.ndarray] = {}
    rows = []
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="aiohal-tick-") as tmp:
        for rate in args.rates:
            period_ns = round(1e9 / rate)
            for method in args.methods:
                for loop_name in (["-"] if method == "thread" else args.loops):
                    lat, meta = run_one(method, rate, loop_name, args.seconds, args.realtime, tmp)
                    stats = summarise(lat, period_ns)
                    rows.append({"method": method, "label": LABELS[method], "loop": loop_name, "rate": rate,
                                 **stats, "rate_hz": meta.get("rate_hz"), "missed": meta.get("missed"),
                                 "cpu": meta.get("cpu_percent"), "meta": meta})
                    if rate == plot_rate and loop_name in ("asyncio", "-") and method != "thread":
                        plot_samples[method] = lat
                    print(f"{method} {rate:g} Hz {loop_name}: {stats['ticks']} ticks, p50 {fmt_us(stats.get('p50'))}",
                          file=sys.stderr, flush=True)
    run_s = time.monotonic() - started

    shown = [{**r, "rate": f"{r['rate']:g}",
              **{key: fmt_us(r.get(key)) for key in ("min", "p50", "p99", "p999", "max", "drift", "last")},
              "missed": "–" if r["missed"] is None else r["missed"]} for r in rows]
    print(table(shown, [
        ("label", "method"), ("loop", "loop"), ("rate", "rate Hz"), ("ticks", "N ticks"),
        ("rate_hz", "achieved Hz"), ("min", "lateness min µs"), ("p50", "p50 µs"), ("p99", "p99 µs"), ("p999", "p99.9 µs"),
        ("max", "max µs"), ("drift", "drift µs"), ("last", "last tick µs"), ("missed", "missed"),
        ("late_1_period", "late ≥ 1 period"), ("cpu", "CPU %"),
    ]))
    print(f"\n{args.seconds:g} s per run, {len(rows)} runs, {run_s:.0f} s in all; "
          f"real-time settings: {'SCHED_FIFO 80 + mlockall' if args.realtime else 'none'}")
    write_json(args.json, {"seconds": args.seconds, "rates": args.rates, "loops": args.loops,
                           "realtime": args.realtime, "run_seconds": round(run_s, 1), "rows": rows})
    if args.plot:
        order = [m for m in ("naive", "abs_sleep", "aiohal", "ticker") if m in plot_samples]
        plot_cdf({m: plot_samples[m] for m in order}, plot_rate, args.plot)


if __name__ == "__main__":
    main()
