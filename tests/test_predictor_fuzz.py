"""No predictor raises on the inputs a live run gives it (session 33).

A raise is not unsafe (the loop logs `predictor_error` and treats the step as "no valid model"), but it is a
defect: a daemon run's first step, frames at rest whose angles differed by float noise, made the variants
with a tail fallback raise "math domain error". Here every predictor kind the stages use, every variant,
with and without the error-aware boundary, gets random live-like step sequences: stop-and-go positions (with
that float-noise jitter at rest), continuous frames, exponential decays with a cliff, lost frames (n = 0),
pose uncertainty with NaN for frames that did not localize."""

from __future__ import annotations

import math

import numpy as np
import pytest

from supervisor.prediction.models import VARIANTS
from supervisor.prediction.predictors import make_predictor
from supervisor.runtime.fits import update_predictor

TRIALS = 150


def _sequence(rng: np.random.Generator, step: float):
    """One run's steps: (xs rad, ns, err (sd_t m, sd_r rad)) per step."""
    continuous = bool(rng.integers(0, 2))
    n0, decay, cliff = rng.uniform(50, 600), rng.uniform(2, 40), rng.uniform(5, 45)  # decay, cliff in degrees
    for k in range(int(rng.integers(1, 31))):
        m = int(rng.integers(1, 8))
        if continuous:
            xs = np.sort(rng.uniform(k * step, (k + 1) * step, m))
        else:
            xs = np.full(m, k * step)
        if k == 0 and rng.integers(0, 2):  # at rest near the start: a tiny angle, frames apart by float noise
            xs = rng.uniform(1e-9, 1e-4) * (1 + rng.normal(0, 1e-10, m) * rng.integers(0, 2))
        deg = np.degrees(xs)
        ns = n0 * np.exp(-deg / decay) * (deg < cliff + rng.normal(0, 2)) + rng.normal(0, 3, m)
        mode = rng.integers(0, 8)
        if mode == 0:
            ns[:] = 0
        elif mode == 1:
            ns[rng.integers(0, m)] = 0
        ns = np.maximum(np.round(ns), 0.0)
        err = np.column_stack([rng.uniform(1e-5, 5e-3, m), rng.uniform(1e-4, 0.2, m)])
        if rng.integers(0, 5) == 0:
            err[rng.integers(0, m)] = np.nan
        yield xs, ns, err


@pytest.mark.parametrize("kind", ["next_step", "long_range"])
def test_no_predictor_raises_on_live_like_inputs(kind):
    rng = np.random.default_rng(20261207)
    raised = []
    for trial in range(TRIALS):
        variant = VARIANTS[trial % len(VARIANTS)]
        aware = bool(rng.integers(0, 2))
        step = math.radians(float(rng.choice([1.0, 1.5])))
        p = make_predictor(kind, variant, float(rng.choice([6, 11, 15, 30])), step,
                           error_kappa=1.0 if aware else None, tolerance_t=0.004, tolerance_r=math.radians(10),
                           local_span=math.radians(6.75), error_span=math.radians(6.75))
        for k, (xs, ns, err) in enumerate(_sequence(rng, step)):
            try:
                update_predictor(p, xs, ns, err)
            except Exception as exc:  # noqa: BLE001 - collected, all reported at once
                raised.append(f"trial {trial} {variant} aware={aware} step {k}: {exc!r} {exc.__notes__}")
                break
    assert not raised, "\n".join(raised)
