"""Stop-and-go's last step (`final_step`): halting a whole step short of theta_allowed, the paper's rule,
or one last, shorter step up to it. Built on the loop fakes (no rendering): n_i falls from 300 with an
e-fold length of 8 deg, so the n_t-15 boundary lies near 24 deg, inside the 30 deg hard limit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from loop_fakes import DEG, build_loop, stage
from supervisor.runtime.loop import FINAL_STEP_MIN, executed_angles, overshoot


def _run(final_step: str, **extra):
    st = stage(sampling="stop_and_go", hard_limit=30 * DEG, warmup_steps=4, final_step=final_step, **extra)
    rig = build_loop(st)
    rec = rig.loop.run()
    executed = executed_angles(rec, rig.kin, rig.T0)
    over, _ = overshoot(np.asarray(rec.trajectory_t), executed, rec.allowance_history)
    steps = [e for e in rig.events.events if e["kind"] == "step"]
    last_pred = [e for e in rig.events.events if e["kind"] == "prediction"][-1]
    return rec, steps, last_pred, over, rig


def test_whole_steps_halt_where_the_arm_is_when_the_next_step_is_refused():
    rec, steps, last_pred, over, _ = _run("whole")
    assert rec.halt_reason == "boundary", rec.halt_reason
    halt = math.degrees(rec.halt_s)
    assert halt == pytest.approx(round(halt / 1.5) * 1.5, abs=1e-6)  # a whole number of steps
    assert not any(e.get("final") for e in steps)
    # refused: the next whole step would pass the allowance in force
    assert halt + 1.5 > last_pred["theta_allowed_deg"] - 1e-9
    assert over <= 1e-9


def test_to_allowance_takes_one_shorter_last_step_up_to_the_allowance_and_no_further():
    whole, *_ = _run("whole")
    rec, steps, last_pred, over, rig = _run("to_allowance")
    assert rec.halt_reason == "boundary", rec.halt_reason
    final = [e for e in steps if e.get("final")]
    assert len(final) == 1 and final[0] is steps[-1]
    allowed = last_pred["theta_allowed_deg"]
    assert last_pred["valid"] and final[0]["target_deg"] == pytest.approx(allowed, abs=1e-9)
    # it started from the whole-step halt, went less than a step further, and ended on the allowance
    assert math.degrees(whole.halt_s) + FINAL_STEP_MIN / DEG - 1e-9 <= math.degrees(rec.halt_s) < \
        math.degrees(whole.halt_s) + 1.5
    assert math.degrees(rec.halt_s) == pytest.approx(allowed, abs=1e-6)
    assert over <= 1e-9  # nothing executed beyond the allowance in force at any tick
    # no frames are taken at the last position: the samples are those of the whole-step run
    assert len(rec.samples) == len(whole.samples)
    # after the guard tripped there is no last step (the allowance is then a stop point, not a boundary)
    rig.loop._guard_stop = rig.loop.follower.state.s
    assert not rig.loop._may_step_to_allowance(rig.loop.follower.state.s - 1.0 * DEG)


def test_a_final_step_clearance_ends_the_last_step_that_far_short_of_the_allowance():
    plain, plain_steps, plain_pred, *_ = _run("to_allowance")
    whole_halt = plain_steps[-2]["target_deg"]  # where the last whole step ended
    room = plain_pred["theta_allowed_deg"] - whole_halt
    assert room > 0.25  # (the fake's boundary leaves room for a last step longer than 0.1 deg + FINAL_STEP_MIN)
    rec, steps, last_pred, over, rig = _run("to_allowance", final_step_clearance=0.1 * DEG)
    assert [e["target_deg"] for e in steps[:-1]] == [e["target_deg"] for e in plain_steps[:-1]]
    assert steps[-1].get("final") and last_pred["theta_allowed_deg"] == pytest.approx(plain_pred["theta_allowed_deg"])
    assert math.degrees(rec.halt_s) == pytest.approx(last_pred["theta_allowed_deg"] - 0.1, abs=1e-6)
    assert rec.halt_reason == "boundary" and over <= 1e-9 and len(rec.samples) == len(plain.samples)
    # a margin that leaves less than FINAL_STEP_MIN of the room: no last step, the arm halts where it is
    rec, steps, *_ = _run("to_allowance", final_step_clearance=(room * DEG - FINAL_STEP_MIN) + 0.01 * DEG)
    assert not any(e.get("final") for e in steps)
    assert math.degrees(rec.halt_s) == pytest.approx(whole_halt, abs=1e-6) and rec.halt_reason == "boundary"
