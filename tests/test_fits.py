"""Where the predictor's fits run: the real clock's fit process against the inline fits of simulated time."""

from __future__ import annotations

import math
import os
import signal
import time

import numpy as np
import pytest

from supervisor.config import load_config
from supervisor.runtime.builder import stage_predictor
from supervisor.runtime.fits import InlineFits, ProcessFits


def _steps(decay: float, n_steps: int = 10) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Five samples per 1.5 deg step of n_i decaying exponentially over `decay` rad, with a pose sd per sample."""
    out = []
    for k in range(n_steps):
        xs = np.full(5, math.radians(1.5 * k))
        out.append((xs, 420.0 * np.exp(-xs / decay) + 2.0, np.full((5, 2), [2e-4, 1e-3])))
    return out


def _wait(fits: ProcessFits, step: int, timeout: float = 30.0):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        done = fits.take(step)
        if done is not None:
            return done
        time.sleep(0.005)
    raise AssertionError(f"no fit for step {step} within {timeout} s")


@pytest.fixture(scope="module")
def fits():
    f = ProcessFits()
    yield f
    f.shutdown()


def _same(a, b) -> None:
    assert a.valid == b.valid and a.reason == b.reason
    assert (math.isnan(a.boundary) and math.isnan(b.boundary)) or a.boundary == pytest.approx(b.boundary, abs=1e-12)


def test_the_fit_process_predicts_what_the_inline_fits_predict(fits):
    stage = load_config(None).stage("explore")  # a cautious fit with the error-aware boundary
    inline = InlineFits(stage_predictor(stage))
    fits.start_run(stage_predictor(stage))
    for k, (xs, ns, err) in enumerate(_steps(0.12)):
        inline.submit(k, xs, ns, err)
        fits.submit(k, xs, ns, err)
        ref, ref_exc = inline.take(k)
        got, exc = _wait(fits, k)
        assert exc is None and ref_exc is None
        _same(got, ref)
    assert got.valid and got.boundary < math.radians(40.0)  # the run got as far as a model that binds


def test_a_new_run_never_takes_an_earlier_runs_fit(fits):
    stage = load_config(None).stage("explore")
    fits.start_run(stage_predictor(stage))
    first = _steps(0.3)  # n_i holds: this run's fits say 45 deg (the hard limit)
    for k, step in enumerate(first):
        fits.submit(k, *step)  # not taken: the run ends with these in flight
    fits.start_run(stage_predictor(stage))  # the next run, on other data
    inline = InlineFits(stage_predictor(stage))
    for k, step in enumerate(_steps(0.12)):  # n_i falls: this run's fits say ~24 deg
        inline.submit(k, *step)
        fits.submit(k, *step)
        got, _ = _wait(fits, k)
        ref = inline.take(k)[0]
        _same(got, ref)
    assert ref.valid and ref.boundary < math.radians(40.0)


def test_a_dead_fit_process_raises_instead_of_never_answering():
    f = ProcessFits()
    try:
        f.start_run(stage_predictor(load_config(None).stage("explore")))
        os.kill(f.pid, signal.SIGKILL)
        t_end = time.monotonic() + 10
        while f._proc.is_alive() and time.monotonic() < t_end:
            time.sleep(0.01)
        with pytest.raises((RuntimeError, BrokenPipeError, OSError)):
            f.submit(0, *_steps(0.12)[0])
            f.take(0)
    finally:
        f.shutdown()


class _RaisingPredictor:
    """A predictor with a bug: its update raises (picklable, for the fit process)."""

    kind = "raising"

    def update(self, xs, ns):
        return math.log(-1.0)  # ValueError: math domain error

    def reset(self):
        pass


def test_a_predictors_exception_reaches_the_loop_from_the_fit_process_with_where_it_was_raised(fits):
    fits.start_run(_RaisingPredictor())
    xs, ns, err = _steps(0.5)[0]
    fits.submit(0, xs, ns, err)
    pred, exc = _wait(fits, 0)
    assert pred is None and isinstance(exc, ValueError) and str(exc) == "math domain error"
    line = _RaisingPredictor.update.__code__.co_firstlineno + 1
    assert len(exc.__notes__) == 1 and exc.__notes__[0].startswith("at ")
    assert exc.__notes__[0].endswith(f"test_fits.py:{line} in update")
