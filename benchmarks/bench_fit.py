"""Time of one artifact-model fit + boundary root find, per variant, with 4, 20 and 200 samples.

Goal (issue 3): < 5 ms median, so an update never delays a 1.5 deg step. Samples come from a
realistic decaying n_i(theta) with 15% multiplicative noise: 4 samples = 4 positions x 1 image,
20 = 10 positions x 2, 200 = 10 positions x 20 (positions 2.25 deg apart). Wall time is reported
with the process CPU time next to it (the CPU column is what a busy shared machine distorts least).

`--accuracy N` adds a side-by-side of the variants on 3N synthetic arcs whose true n(theta) is
not always an EMG (EMG, stretched exponential, plateau + logistic drop; 10 images per position
every 2.25 deg, 5-15% noise per position and per image; "failure" where the true mean falls to 10):
the signed error of theta_p for n_t = 15 predicted two positions before the true crossing
(> 0 = late, non-conservative), and the next-step rule's maximum mean SPL at zero incursion over
n_t = 4..200 (the static envelope's for reference).

    .venv/bin/python benchmarks/bench_fit.py [--repeats 30] [--variants paper,logfit_lcb] [--accuracy 10]
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


STEP, X_MAX, N_FAIL = 2.25, 45.0, 10.0
POSITIONS = np.arange(0.0, X_MAX + 1e-9, STEP)


def synthetic_arc(family: str, rng: np.random.Generator):
    """(true mean curve, x, n) for one synthetic arc of the given family."""
    n0, x_fail = rng.uniform(300, 800), rng.uniform(20, 50)
    if family == "emg":
        K, mu = rng.uniform(3, 15), rng.uniform(-3, 8)
        a = n0 / emg(np.linspace(-5, 60, 651), 1.0, K, mu).max()
        f = lambda x: emg(x, a, K, mu)  # noqa: E731
    elif family == "stretched":
        p = rng.uniform(1.2, 3.0)
        s = x_fail / np.log(n0 / N_FAIL) ** (1 / p)
        f = lambda x: n0 * np.exp(-(np.maximum(x, 0) / s) ** p)  # noqa: E731
    else:
        w = rng.uniform(2, 6)
        c = x_fail - w * np.log(n0 / N_FAIL - 1)
        f = lambda x: n0 / (1 + np.exp((x - c) / w))  # noqa: E731
    sp, si = rng.uniform(0.05, 0.15), rng.uniform(0.05, 0.15)
    x = np.repeat(POSITIONS, 10)
    bump = np.repeat(np.exp(sp * rng.standard_normal(len(POSITIONS))), 10)
    n = np.round(f(x) * bump * np.exp(si * rng.standard_normal(len(x))))
    n[n < 6] = 0  # lost frames
    return f, x, n


def crossing(f, level: float) -> float:
    g = np.linspace(0.0, X_MAX, 4501)
    v = f(g)
    i = np.flatnonzero((v <= level) & (g >= g[np.argmax(v)]))
    return X_MAX if len(i) == 0 else float(g[i[0]])


def accuracy(variants: list[str], per_family: int) -> None:
    rng = np.random.default_rng(0)
    arcs = [synthetic_arc(fam, rng) for fam in ("emg", "stretched", "logistic") for _ in range(per_family)]
    actual = np.array([crossing(f, N_FAIL) for f, _, _ in arcs])
    n_t = np.arange(4, 201, 2)
    print(f"\n{len(arcs)} synthetic arcs; mean theta_a {actual.mean():.1f} deg")
    print(f"{'variant':<12} {'median err':>10} {'late':>6} {'late>2':>7} {'invalid':>8} {'max SPL@R_i=0':>14} "
          f"{'n_t':>4}")
    for variant in variants:
        errs, stops = [], []
        for f, x, n in arcs:
            fits = [fit_variant(variant, x[x <= p + 1e-9], n[x <= p + 1e-9]) if k >= 3 else None
                    for k, p in enumerate(POSITIONS)]
            c15 = crossing(f, 15.0)
            k2 = int(np.floor(c15 / STEP)) - 2
            if k2 >= 3 and c15 < X_MAX:
                mf = fits[k2]
                errs.append(mf.boundary(15, POSITIONS[k2], X_MAX) - c15 if mf.ok else np.nan)
            row = []
            for nt in n_t:
                stop = X_MAX
                for k in range(3, len(POSITIONS)):  # warm-up: the first 4 positions
                    mf = fits[k]
                    if not mf.ok or mf.boundary(nt, POSITIONS[k], X_MAX) <= POSITIONS[k] + STEP - 1e-12:
                        stop = POSITIONS[k]
                        break
                row.append(stop)
            stops.append(row)
        e = np.array(errs)
        ok = e[np.isfinite(e)]
        S = np.array(stops)
        spl = np.minimum(S, actual[:, None]).mean(0)
        safe = np.flatnonzero((S <= actual[:, None] + 1e-9).all(0))
        best = (f"{spl[safe].max():>14.1f} {n_t[safe[np.argmax(spl[safe])]]:>4}" if len(safe)
                else f"{'none':>14} {'-':>4}")
        print(f"{variant:<12} {np.median(ok):>+10.1f} {np.mean(ok > 0):>6.0%} {np.mean(ok > 2):>7.0%} "
              f"{int(np.sum(~np.isfinite(e))):>8} {best}")
    env = np.arange(0.0, X_MAX + 1e-9, 0.25)
    safe_env = [e for e in env if np.all(e <= actual + 1e-9)]
    print(f"{'static':<12} {'':>10} {'':>6} {'':>7} {'':>8} {np.mean(np.minimum(max(safe_env), actual)):>14.1f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--accuracy", type=int, default=0, metavar="N", help="also compare on 3N synthetic arcs")
    a = ap.parse_args()
    print(f"{'variant':<12} {'samples':>7} {'median ms':>10} {'p90 ms':>8} {'cpu ms':>7} {'valid':>6}")
    for variant in a.variants.split(","):
        for n in (4, 20, 200):
            times, cpu, valid = [], [], 0
            rng = np.random.default_rng(n)  # the same sample sets for every variant
            for _ in range(a.repeats):
                x, y = samples(n, rng)
                t0, c0 = time.perf_counter(), time.process_time()
                mf = fit_variant(variant, x, y)
                if mf.ok:
                    mf.boundary(15, float(x.max()), 45.0)
                    valid += 1
                times.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            times.sort()
            print(f"{variant:<12} {n:>7} {statistics.median(times) * 1000:>10.2f} "
                  f"{times[int(0.9 * (len(times) - 1))] * 1000:>8.2f} {statistics.median(cpu) * 1000:>7.2f} "
                  f"{valid:>3}/{a.repeats}")
    if a.accuracy > 0:
        accuracy(a.variants.split(","), a.accuracy)
    return 0


if __name__ == "__main__":
    sys.exit(main())
