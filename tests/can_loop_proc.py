"""A control loop on the real clock (sim robot, plain camera, geometric worker: no rendering) sending its CAN
heartbeat from its ticks, as a process of its own: `tests/test_can_process.py` SIGKILLs it mid-motion.

Usage: python can_loop_proc.py CONFIG   (prints "ready", waits for a line on stdin, prints "moving" at speed)
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from loop_fakes import DEG, PlainCamera, build_loop, stage  # noqa: E402
from supervisor.can.channel import SideChannel  # noqa: E402
from supervisor.clock import MonotonicClock  # noqa: E402
from supervisor.config import load_config  # noqa: E402
from supervisor.motion.braking import PathLimits  # noqa: E402
from supervisor.runtime.pacer import TickPacer  # noqa: E402


def main() -> int:
    settings = load_config(sys.argv[1]).can
    ch = SideChannel(settings)
    ch.open()
    ch.set_state("moving", 0)
    clock = MonotonicClock()
    # slow and tolerant: a long motion that a loaded machine does not fault on its own
    st = stage(hard_limit=45 * DEG, limits=PathLimits(2 * DEG, 20 * DEG, 200 * DEG), overrun_budget=100000,
               pose_gap=0.5, frame_timeout=5.0, localization_timeout=5.0)
    rig = build_loop(st, clock=clock, pacer=TickPacer(clock, 0.001, st.overrun_budget), camera=PlainCamera(clock))
    ticks = [0]

    def beat(now: float) -> None:
        ch.heartbeat(now)
        ticks[0] += 1
        if ticks[0] == 500:
            print("moving", flush=True)

    rig.loop.heartbeat, rig.loop.on_brake = beat, ch.stop
    print("ready", flush=True)
    sys.stdin.readline()
    rec = rig.loop.run(max_time=120.0)
    print("ended", rec.halt_reason, flush=True)
    ch.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
