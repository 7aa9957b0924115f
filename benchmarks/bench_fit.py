"""Time of one artifact-model fit + boundary root find, per variant, with 4, 20 and 200 samples.

Goal (issue 3): < 5 ms median, so an update never delays a 1.5 deg step. Samples come from a
realistic decaying n_i(theta) with 15% multiplicative noise (10 images per 2.25 deg position).

    .venv/bin/python benchmarks/bench_fit.py [--repeats 30]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from supervisor.prediction.emg import emg  # noqa: E402
from supervisor.prediction.models import VARIANTS, fit_variant  # noqa: E402


def samples(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    per = max(1, n // 10) if n >= 20 else 1
    positions = np.arange(n // per) * 2.25
    x = np.repeat(positions, per)[:n]
    y = emg(x, 6000.0, 9.0, -1.0) * np.exp(0.15 * rng.standard_normal(len(x)))
    return x, y


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    print(f"{'variant':<12} {'samples':>7} {'median ms':>10} {'p90 ms':>8} {'valid':>6}")
    for variant in VARIANTS:
        for n in (4, 20, 200):
            times, valid = [], 0
            for _ in range(a.repeats):
                x, y = samples(n, rng)
                t0 = time.perf_counter()
                mf = fit_variant(variant, x, y)
                if mf.ok:
                    mf.boundary(15, float(x.max()), 45.0)
                    valid += 1
                times.append(time.perf_counter() - t0)
            times.sort()
            print(f"{variant:<12} {n:>7} {statistics.median(times) * 1000:>10.2f} "
                  f"{times[int(0.9 * (len(times) - 1))] * 1000:>8.2f} {valid:>3}/{a.repeats}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
