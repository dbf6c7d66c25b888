"""How often the host takes this CPU away: the floor under every lateness figure.

A thread spins on ``time.monotonic_ns()``, pinned to one CPU, for ``--seconds`` (normal
scheduling: at SCHED_FIFO a spin that never sleeps is throttled by the kernel for 50 ms of
every second, ``sched_rt_runtime_us``; ``--fifo`` shows it), and records every gap between two consecutive reads longer than 2 µs. A
gap is time this CPU ran something else: the hypervisor (steal), an interrupt, the kernel. A
loop that spins to its deadline (precision mode) is late by the rest of any gap that spans
the deadline, so the share of time spent inside gaps longer than X bounds how many ticks can
be on time within X: if gaps longer than 5 µs cover 2 % of the time, no loop on this machine
can have a lateness p99 of 5 µs, whatever its code.

    python -m benchmarks.host_gaps [--seconds 10] [--cpu 0] [--fifo] [--json PATH]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from .common import StealMeter, table, write_json

THRESHOLDS_US = (2, 5, 10, 50, 1000)


def spin(seconds: float, cpu: int, fifo: bool = False) -> tuple[np.ndarray, float]:
    """Gaps (ns) longer than 2 µs while spinning ``seconds`` on ``cpu``; and the host's steal (%)."""
    os.sched_setaffinity(0, {cpu})
    if fifo:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80))
    steal = StealMeter()
    mono = time.monotonic_ns
    gaps = np.zeros(2_000_000, dtype=np.int64)
    n = 0
    start = last = mono()
    end = start + int(seconds * 1e9)
    while last < end:
        now = mono()
        if now - last > 2000 and n < len(gaps):
            gaps[n] = now - last
            n += 1
        last = now
    return gaps[:n], steal.percent()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--cpu", type=int, default=0)
    p.add_argument("--fifo", action="store_true", help="spin at SCHED_FIFO 80 (throttled 5 %% of the time)")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    gaps, steal = spin(args.seconds, args.cpu, args.fifo)
    total_ns = args.seconds * 1e9
    rows = []
    for us in THRESHOLDS_US:
        longer = gaps[gaps > us * 1000]
        rows.append({"gap_over_us": us, "per_second": round(len(longer) / args.seconds, 1),
                     "time_share_percent": round(100 * float(longer.sum()) / total_ns, 3)})
    print(f"spinning {args.seconds:g} s on CPU {args.cpu}: {len(gaps)} gaps over 2 µs, longest "
          f"{gaps.max() / 1e3 if len(gaps) else 0:.0f} µs, host steal {steal:.1f} %")
    print(table(rows, [("gap_over_us", "gap over µs"), ("per_second", "per second"),
                       ("time_share_percent", "share of time %")]))
    write_json(args.json, {"benchmark": "host_gaps", "seconds": args.seconds, "steal_percent": round(steal, 2),
                           "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
