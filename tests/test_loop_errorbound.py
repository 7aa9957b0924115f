"""The error-aware boundary in the live loop: the step's pose uncertainty reaches the predictor, and the
halt says when the error bound (not n_i) stopped the arc. Built on the loop fakes (no rendering)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from loop_fakes import DEG, GeometricWorker, build_loop, n_of_theta, stage
from supervisor.localization.artifacts import viewing_angle
from supervisor.motion.braking import PathLimits
from supervisor.prediction.errorbound import ERR_SPAN
from supervisor.prediction.models import LOCAL_SPAN
from supervisor.prediction.predictors import ErrorAwarePredictor, NextStepPredictor
from supervisor.runtime.builder import stage_predictor



def sd_of_theta(theta: float) -> float:
    """A translation spread that grows 20-fold over 9 deg: 0.1 mm at the start, 2 mm at 9 deg."""
    return 1e-4 * math.exp(theta / (9 * DEG) * math.log(20))


class UncertainWorker(GeometricWorker):
    """The geometric worker whose results also carry the pose spread (sd_t from the angle, sd_r small),
    or none at all (`with_sd=False`: nan, as when the localizer could not compute it)."""

    def __init__(self, *a, with_sd: bool = True, **k) -> None:
        super().__init__(*a, **k)
        self.with_sd = with_sd

    def submit(self, job, hint) -> bool:
        super().submit(job, hint)
        jr = self._pending[-1]
        theta = viewing_angle(self.T_base_cam_model, job.T_base_cam)
        sd_t, sd_r = (sd_of_theta(theta), 0.01 * DEG) if self.with_sd else (math.nan, math.nan)
        self._pending[-1] = replace(jr, result=replace(jr.result, sd_t=sd_t, sd_r=sd_r))
        return True


def _rig(st, with_sd: bool = True):
    rig = build_loop(st)
    w = rig.loop.worker
    rig.loop.worker = UncertainWorker(w.T_base_target, w.T_base_cam_model, w.latency, with_sd=with_sd)
    rig.loop.predictor = stage_predictor(st)  # as the builder wires it
    return rig


FAST = PathLimits(30 * DEG, 200 * DEG, 2000 * DEG)  # a quick arc keeps the test short
ERR_STAGE = dict(hard_limit=45 * DEG, sampling="stop_and_go", tolerance_t=0.004, tolerance_r=10 * DEG,
                 error_kappa=2.0, limits=FAST)


def test_the_stage_keys_build_the_error_aware_predictor():
    p = stage_predictor(stage(**ERR_STAGE))
    assert isinstance(p, ErrorAwarePredictor) and isinstance(p.base, NextStepPredictor)
    assert (p.tol_t, p.tol_r, p.kappa) == (0.004, 10 * DEG, 2.0)
    # by angle, whatever the sampling: what the replay's 4 positions at the recording's 2.25 deg step span
    for sampling in ("stop_and_go", "continuous"):
        p = stage_predictor(stage(**{**ERR_STAGE, "sampling": sampling}))
        assert p.span == pytest.approx(math.radians(ERR_SPAN))
        assert p.base.local_span == pytest.approx(LOCAL_SPAN)  # fit units (deg)
    assert isinstance(stage_predictor(stage()), NextStepPredictor)  # no error_kappa: n_i only


def test_the_error_bound_stops_before_n_i_would_and_says_so():
    st = stage(**ERR_STAGE)
    rig = _rig(st)
    rec = rig.loop.run()
    assert rec.halt_reason == "error_bound", rec.halt_reason
    assert not rig.events.of_kind("fault")
    # kappa * sd reaches the 4 mm tolerance at 9 deg: the arc halts before it, long before n_i's 24 deg
    assert rec.halt_s < 9 * DEG
    assert rec.halt_s > st.warmup_steps * st.step
    assert n_of_theta(rec.halt_s) > 2 * st.n_t  # n_i alone saw no reason to stop
    assert max(rec.trajectory_s) <= rec.s_allowed_at_brake + 1e-9
    last = rig.events.of_kind("prediction")[-1]
    assert last["limited_by"] == "error_bound"
    # the samples carried the spread to the predictor
    assert all(s.sd_t == pytest.approx(sd_of_theta(s.theta)) for s in rec.samples)
    assert len(rig.loop.predictor._x) == len({s.step for s in rec.samples})

    # n_i's own model, fitted on the same samples, puts its boundary far beyond the halt
    base = rig.loop.predictor.base.last
    assert base.valid and base.allow_next and base.boundary > rec.halt_s + 8 * DEG

    # the same arc without the error bound runs on (to the 15 deg end of this shortened arc)
    plain = _rig(stage(**{**ERR_STAGE, "error_kappa": None, "hard_limit": 15 * DEG}))
    rec2 = plain.loop.run()
    assert rec2.halt_reason in ("boundary", "end_of_path")
    assert rec2.halt_s > rec.halt_s + 5 * DEG


def test_a_smaller_kappa_goes_further():
    far = _rig(stage(**{**ERR_STAGE, "error_kappa": 0.5})).loop.run()
    near = _rig(stage(**ERR_STAGE)).loop.run()
    assert far.halt_s > near.halt_s + 2 * DEG and far.halt_reason == "error_bound"


def test_without_a_pose_uncertainty_the_error_bound_permits_nothing_beyond_the_warmup():
    st = stage(**ERR_STAGE)
    rig = _rig(st, with_sd=False)
    rec = rig.loop.run()
    assert rec.halt_reason == "error_bound"
    assert rec.halt_s == pytest.approx(st.warmup_steps * st.step, abs=1e-9)
    assert not np.any(rig.sim.state().dq)
