"""The whole supervisor on the wall clock: sim robot and sim camera (render process), capture thread,
localization processes, paced tick (250 Hz), through the same builder as the dry-run."""

from __future__ import annotations

import dataclasses
import math

import pytest

from supervisor.config import load_config
from supervisor.dryrun import DryRunSpec, run_dry_run


@pytest.mark.slow
def test_realtime_dry_run_halts_latched_without_overshoot(tmp_path):
    cfg = load_config(None)
    st = dataclasses.replace(cfg.stage("explore"), hard_limit=math.radians(4.5), frames_per_step=2,
                             warmup_steps=2, frame_timeout=1.0, localization_timeout=5.0)  # a loaded machine is slow
    cfg = dataclasses.replace(cfg, stages={**cfg.stages, "short": dataclasses.replace(st, name="short")})
    s = run_dry_run(cfg, DryRunSpec(stage="short", azimuth=math.radians(90.0), oracle=False), tmp_path,
                    progress=lambda m: None, realtime=True)
    assert s["realtime"] is True and "simulated_time_s" not in s
    # On a quiet machine the arc runs to its 4.5 deg end; on a starved one the supervisor may fault
    # (camera timeout, overruns): either way it halts latched and never passes what was allowed.
    if not s["faults"]:
        assert s["halt_reason"] == "end_of_path" and s["halt_angle_deg"] == pytest.approx(4.5, abs=1e-6)
        assert s["ticks"]["ticks"] > 250  # paced at the configured 250 Hz for seconds
    else:
        assert s["halt_reason"].startswith("fault:")
    assert s["max_overshoot_deg"] is None or s["max_overshoot_deg"] <= 1e-6  # None: halted before any tick
    assert (tmp_path / "events.jsonl").read_text().count('"kind": "halted"') == 1


def test_realtime_setup_lifts_light_threads_and_puts_every_thread_back():
    """The tick's thread and the process's other threads go real-time for a run, but for the thread worker's
    localizers; afterwards every thread is as it was."""
    import os
    import threading

    from supervisor.runtime.builder import realtime_thread_restore, realtime_thread_setup

    stop = threading.Event()
    threads = {name: threading.Thread(target=stop.wait, name=name, daemon=True)
               for name in ("capture", "event-writer", "predictor", "localize-0", "session-writer")}
    for t in threads.values():
        t.start()

    def policy(t) -> int:
        return os.sched_getscheduler(t.native_id)

    before = {n: (policy(t), os.sched_getparam(t.native_id).sched_priority) for n, t in threads.items()}
    main_before = os.sched_getscheduler(0)
    try:
        setup = realtime_thread_setup()
        try:
            if not setup["sched_fifo"]:
                assert setup["_helpers"] == []  # unprivileged: nothing else is touched either
            else:
                assert os.sched_getscheduler(0) == os.SCHED_FIFO
                for name in ("capture", "event-writer", "predictor", "session-writer"):
                    assert policy(threads[name]) == os.SCHED_FIFO, name
                    assert os.sched_getparam(threads[name].native_id).sched_priority == 1
                for name in ("localize-0",):
                    assert policy(threads[name]) == before[name][0], name
        finally:
            realtime_thread_restore(setup)
        assert os.sched_getscheduler(0) == main_before
        assert {n: (policy(t), os.sched_getparam(t.native_id).sched_priority) for n, t in threads.items()} == before
    finally:
        stop.set()


def test_a_runs_setup_and_restore_leave_the_gil_switch_interval_exactly_as_it_was():
    """The daemon serves at the tick's own interval (0.2 ms); every run saves and restores it. CPython keeps it
    in truncated microseconds: restored as read back, it lost a microsecond per run (200 -> 199 -> 198 µs)."""
    import sys

    from supervisor.runtime.builder import SWITCH_INTERVAL, realtime_thread_restore, realtime_thread_setup, \
        set_switch_interval

    before = sys.getswitchinterval()
    try:
        for start_us in (200, 199, 1000, 4999):
            set_switch_interval(start_us / 1e6)
            for _ in range(5):
                setup = realtime_thread_setup(helpers=None)
                assert round(sys.getswitchinterval() * 1e6) == round(SWITCH_INTERVAL * 1e6)
                realtime_thread_restore(setup)
                assert round(sys.getswitchinterval() * 1e6) == start_us
    finally:
        sys.setswitchinterval(before)
