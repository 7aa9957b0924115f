"""The franka driver on franky-sim: tracking lag per command scheme, the stop's braking, link-loss notice.

Each scheme streams the supervisor's own path - the default arc (10 deg/s, 20 deg/s^2,
200 deg/s^3 on the arc angle, camera 0.35 m from its pivot), planned by Ruckig and
mapped to joints by PathFollower beforehand - one joint target per tick on the real
clock, reading `state()` every tick as the supervisor does. Lag = arrival time of a
reported joint state minus the time its position was commanded (the reported q located
on the commanded path, interpolated between ticks), where the path moves at >= 25% of
its peak speed. Then: the stop's braking distance from cruise against a Ruckig joint brake with
the arm's datasheet limits from the same state; the flange pose the controller reports
against our kinematics; and, after SIGKILL of franky-sim mid-motion, when the caller's
20 ms age rule fires, when state() raises, and how long a new robot object takes.

    .venv/bin/python benchmarks/bench_franka.py [--host 127.0.0.60] [--arc-deg 8] [--quick]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
from ruckig import ControlInterface, InputParameter, Result, Ruckig, Trajectory

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.robot.franka import FrankaRobot  # noqa: E402
from sim.fci_server import FciServer  # noqa: E402
from supervisor.arm.kinematics import PandaKinematics  # noqa: E402
from supervisor.errors import SupervisorError  # noqa: E402
from supervisor.geometry import make_T, pose_error  # noqa: E402
from supervisor.motion.braking import PathLimits  # noqa: E402
from supervisor.motion.paths import ArcPath  # noqa: E402
from supervisor.motion.plan import PathFollower  # noqa: E402

DEG = math.pi / 180.0
LIMITS = PathLimits(10 * DEG, 20 * DEG, 200 * DEG)
Q_START = np.radians([0, -45, 0, -135, 0, 90, 45])
T_FLANGE_CAM = make_T(np.eye(3), [0.05, 0.0, 0.05])
STATE_GAP = 0.020  # s, the supervisor's robot-state age rule


def arc_joint_path(kin: PandaKinematics, dt: float, arc: float, q0: np.ndarray = Q_START) -> np.ndarray:
    """The supervisor's arc from `q0` to `arc` rad as joint targets, one per tick of `dt`, ending at rest."""
    T0 = kin.fk(q0, "camera")
    path = ArcPath(T0, T0[:3, 3] + 0.35 * T0[:3, 2], 90 * DEG)
    f = PathFollower(path, LIMITS, kin, q0, dt)
    qs = [f.q.copy()]
    while True:
        *_, q = f.tick(arc)
        qs.append(np.array(q))
        if f.tracker.at_rest and f.state.s >= arc - 1e-9:
            break
    return np.array(qs)


def joint_move(kin: PandaKinematics, q0: np.ndarray, q1: np.ndarray, dt: float, scale: float = 0.2) -> np.ndarray:
    """A Ruckig joint move q0 -> q1 at `scale` of the datasheet limits, sampled every `dt`."""
    otg = Ruckig(7)
    inp = InputParameter(7)
    inp.current_position, inp.target_position = q0.tolist(), q1.tolist()
    inp.max_velocity = (kin.dq_max * scale).tolist()
    inp.max_acceleration = (kin.ddq_max * scale).tolist()
    inp.max_jerk = (kin.dddq_max * scale).tolist()
    tr = Trajectory(7)
    otg.calculate(inp, tr)
    return np.array([tr.at_time(t)[0] for t in np.arange(0.0, tr.duration + dt, dt)])


def stream(robot: FrankaRobot, qs: np.ndarray, dt: float, hold_s: float = 0.3, kill=None) -> dict:
    """Send `qs` one per `dt` on the real clock (state() then command() each tick); then hold the last target."""
    t_cmd, states, late, cost = [], [], 0, []
    n = len(qs) + int(hold_s / dt)
    t0 = time.monotonic()
    for k in range(n):
        deadline = t0 + k * dt
        now = time.monotonic()
        if now < deadline:
            time.sleep(deadline - now)
        elif now - deadline > dt:
            late += 1
        if kill is not None and kill(k):
            kill = None
        c0 = time.perf_counter()
        st = robot.state()
        q = qs[min(k, len(qs) - 1)]
        robot.command(q)
        cost.append(time.perf_counter() - c0)
        t_cmd.append(time.monotonic())
        states.append((time.monotonic(), st))
    return {"t_cmd": np.array(t_cmd), "states": states, "late": late, "qs": qs, "cost": np.array(cost)}


def lag_ms(run: dict, min_speed: float = 0.25) -> np.ndarray:
    """Per fresh reported state: its arrival time minus when its position was commanded.

    Counted where the commanded path moves at >= `min_speed` of its peak speed (near rest a
    position error of a few micro-radians reads as a long time lag).
    """
    qs, t_cmd = run["qs"], run["t_cmd"][: len(run["qs"])]
    speed = np.r_[np.linalg.norm(np.diff(qs, axis=0), axis=1), 0.0]
    moving = speed >= min_speed * speed.max()
    seen, out = set(), []
    for _, st in run["states"]:
        if st.seq in seen:
            continue
        seen.add(st.seq)
        dist = np.linalg.norm(qs - st.q, axis=1)
        k = int(np.argmin(dist))
        if not moving[k] or k + 1 >= len(qs):
            continue
        # sub-tick: project onto the segment toward the neighbour on the other side
        j = k + 1 if k == 0 or dist[k + 1] < dist[k - 1] else k - 1
        seg = qs[j] - qs[k]
        frac = float(np.clip((st.q - qs[k]) @ seg / (seg @ seg), 0.0, 1.0))
        out.append((st.t - (t_cmd[k] + frac * (t_cmd[j] - t_cmd[k]))) * 1000.0)
    return np.array(out)


def robot_rate(run: dict) -> float:
    """Robot (simulated) seconds per host second over the run."""
    first, last = run["states"][0][1], run["states"][-1][1]
    return (last.robot_time - first.robot_time) / max(last.t - first.t, 1e-9)


def go_to(robot: FrankaRobot, kin: PandaKinematics, q: np.ndarray, dt: float) -> None:
    robot.stop()
    robot.move_to(q, speed=0.3)
    time.sleep(0.1)


def scheme_runs(host: str, kin: PandaKinematics, schemes: list[dict], arc: float, repeats: int) -> None:
    print(f"{'scheme':<44} {'lag p50 ms':>10} {'p99 ms':>8} {'final mrad':>10} {'over mrad':>9} "
          f"{'motions':>7} {'late':>5} {'sim rt':>6} {'max age ms':>10} {'tick us p50/p99':>16}")
    for spec in [dict(s) for s in schemes for _ in range(repeats)]:
        dt = spec.pop("dt")
        name = f"{spec['command_mode']} @{1 / dt:.0f} Hz ticks, send {1 / spec['send_period']:.0f} Hz" + (
            f", K {spec['gain']:.0f}" if spec["command_mode"] == "velocity" else "")
        if spec["command_mode"] == "impedance":
            name = f"franky joint impedance @{1 / dt:.0f} Hz (torque)"
        try:
            with FrankaRobot(kin, host, control_period=dt, max_tracking_error=0.5, link_timeout=1.0,
                             **(spec if spec["command_mode"] != "impedance" else {})) as robot:
                go_to(robot, kin, Q_START, dt)
                qs = arc_joint_path(kin, dt, arc)
                robot.motions_sent = 0
                if spec["command_mode"] == "impedance":
                    robot.close()
                    run = impedance_run(host, kin, arc, dt, spec["stiffness"])
                else:
                    run = stream(robot, qs, dt, hold_s=0.4)
                lag = lag_ms(run)
                qf = run["states"][-1][1].q
                age = max(t - st.t for t, st in run["states"]) * 1e3
                c = run.get("cost")
                tick = "-" if c is None else f"{np.median(c) * 1e6:.0f}/{np.percentile(c, 99) * 1e6:.0f}"
                reported = np.array([st.q for _, st in run["states"]])
                along = (reported - qs[0]) @ (qs[-1] - qs[0]) / np.linalg.norm(qs[-1] - qs[0])
                over = max(0.0, along.max() - np.linalg.norm(qs[-1] - qs[0]))
                print(f"{name:<44} {np.percentile(lag, 50):>10.1f} {np.percentile(lag, 99):>8.1f} "
                      f"{np.abs(qf - qs[-1]).max() * 1e3:>10.2f} {over * 1e3:>9.2f} {robot.motions_sent:>7d} "
                      f"{run['late']:>5d} {robot_rate(run):>6.2f} {age:>10.1f} {tick:>16}")
                if not robot.closed:
                    robot.stop()
        except SupervisorError as exc:
            print(f"{name:<44} FAILED: {exc}")


def impedance_run(host: str, kin: PandaKinematics, arc: float, dt: float, stiffness: np.ndarray) -> dict:
    """franky's streaming joint-impedance tracker (torque control) fed the same targets, outside our driver."""
    import franky
    from supervisor.arm.state import RobotState

    with FrankaRobot(kin, host, control_period=dt) as robot:
        go_to(robot, kin, Q_START, dt)
    fr = franky.Robot(host, realtime_config=franky.RealtimeConfig.Ignore)
    qs = arc_joint_path(kin, dt, arc)
    motion = franky.JointImpedanceTrackingMotion(stiffness=stiffness)
    motion.set_reference(franky.JointReference(q=fr.current_joint_positions))
    fr.move(motion, asynchronous=True)
    t_cmd, states, fresh = [], [], {}
    t0 = time.monotonic()
    for k in range(len(qs) + int(0.4 / dt)):
        delay = t0 + k * dt - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        raw = fr.state
        ms = int(raw.time.to_msec())
        fresh.setdefault(ms, time.monotonic())
        q = np.array(raw.q)
        states.append((time.monotonic(), RobotState(fresh[ms], ms, q, np.array(raw.dq), np.eye(4), ms / 1000)))
        j = min(k, len(qs) - 1)
        dq = (qs[j] - qs[j - 1]) / dt if 0 < k < len(qs) else np.zeros(7)
        motion.set_reference(franky.JointReference(q=qs[j], dq=dq))
        t_cmd.append(time.monotonic())
    fr.stop()
    return {"t_cmd": np.array(t_cmd), "states": states, "late": 0, "qs": qs}


def ruckig_brake_distance(q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, v_max: np.ndarray, a_max: np.ndarray,
                          j_max: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-joint distance and duration of a time-optimal Ruckig brake to rest within the given limits."""
    otg = Ruckig(7)
    inp = InputParameter(7)
    inp.control_interface = ControlInterface.Velocity
    inp.current_position, inp.current_velocity = q.tolist(), dq.tolist()
    inp.current_acceleration = np.clip(ddq, -a_max, a_max).tolist()
    inp.target_velocity, inp.target_acceleration = [0.0] * 7, [0.0] * 7
    inp.max_velocity = np.maximum(v_max, np.abs(dq)).tolist()
    inp.max_acceleration, inp.max_jerk = a_max.tolist(), j_max.tolist()
    tr = Trajectory(7)
    if otg.calculate(inp, tr) not in (Result.Working, Result.Finished):
        raise RuntimeError("ruckig brake failed")
    return np.array(tr.at_time(tr.duration)[0]) - q, tr.duration


def braking(host: str, kin: PandaKinematics, dt: float, repeats: int) -> None:
    print(f"\nstop() from cruise ({repeats} runs): braking distance along the motion, |dq| at the stop call")
    with FrankaRobot(kin, host, control_period=dt, max_tracking_error=0.5, link_timeout=1.0) as robot:
        for r in range(repeats):
            go_to(robot, kin, Q_START, dt)
            q_far = Q_START + np.array([0.3, 0.2, -0.2, 0.2, 0.2, -0.2, 0.3])
            qs = joint_move(kin, Q_START, q_far, dt, scale=0.15)
            cut = len(qs) // 2
            run = stream(robot, qs[:cut], dt, hold_s=0.0)
            st = robot.state()
            raw = robot._raw
            ddq = np.array(raw.ddq_d, dtype=float)
            c0 = time.monotonic()
            robot.stop()
            took = time.monotonic() - c0
            time.sleep(0.2)
            end = robot.state()
            u = st.dq / np.linalg.norm(st.dq)
            actual = (end.q - st.q) @ u
            f = robot.relative_dynamics_factor
            pred, dur = ruckig_brake_distance(st.q, st.dq, ddq, kin.dq_max, kin.ddq_max * f, kin.dddq_max * f)
            print(f"  run {r}: |dq| {np.linalg.norm(st.dq):.3f} rad/s, measured {actual * 1e3:.2f} mrad, "
                  f"Ruckig with the {kin.arm} datasheet {pred @ u * 1e3:.2f} mrad in {dur * 1e3:.0f} ms; stop() returned after {took * 1e3:.0f} ms, "
                  f"rest |dq| {np.abs(end.dq).max():.4f}, reversed {bool(actual < 0)}")
            del run


def idle_reads(host: str, kin: PandaKinematics, n: int = 500) -> None:
    print("\nstate() at rest, one read per ms:")
    for hold in (True, False):
        with FrankaRobot(kin, host, idle_hold=hold) as robot:
            cost = []
            for _ in range(n):
                c0 = time.perf_counter()
                robot.state()
                cost.append(time.perf_counter() - c0)
                time.sleep(0.001)
            c = np.array(cost) * 1e6
            print(f"  idle_hold={hold!s:<5}: median {np.median(c):.0f} us, p99 {np.percentile(c, 99):.0f} us, "
                  f"max {c.max():.0f} us")


def rest_link_loss(host: str, kin: PandaKinematics) -> None:
    srv = FciServer(host)
    gap = None
    try:
        robot = FrankaRobot(kin, host)
        time.sleep(0.05)
        srv.kill()
        tk = time.monotonic()
        while True:
            try:
                st = robot.state()
            except SupervisorError as exc:
                print(f"  at rest (idle hold): driver raised {type(exc).__name__} {(time.monotonic() - tk) * 1e3:.1f} "
                      "ms after the kill")
                break
            if time.monotonic() - st.t > STATE_GAP and gap is None:
                gap = time.monotonic()
                print(f"  at rest (idle hold): caller's 20 ms age rule fired {(gap - tk) * 1e3:.1f} ms after the kill")
            time.sleep(0.001)
    finally:
        srv.kill()


def link_loss(host: str, kin: PandaKinematics, dt: float) -> None:
    print("\nlink loss: SIGKILL franky-sim mid-motion, state() and command() every tick")
    srv = FciServer(host)
    try:
        robot = FrankaRobot(kin, host, control_period=dt)
        go_to(robot, kin, Q_START, dt)
        qs = arc_joint_path(kin, dt, 8 * DEG)
        killed = {}

        def kill(k: int) -> bool:
            if k == len(qs) // 2:
                srv.kill()
                killed["t"] = time.monotonic()
                return True
            return False

        gap_at = raised_at = None
        err = None
        t0 = time.monotonic()
        k = 0
        try:
            while time.monotonic() - t0 < 5.0:
                deadline = t0 + k * dt
                if time.monotonic() < deadline:
                    time.sleep(deadline - time.monotonic())
                kill(k)
                st = robot.state()
                now = time.monotonic()
                if "t" in killed and gap_at is None and now - st.t > STATE_GAP:
                    gap_at = now
                robot.command(qs[min(k, len(qs) - 1)])
                k += 1
        except SupervisorError as exc:
            raised_at, err = time.monotonic(), exc
        tk = killed["t"]
        print(f"  caller's 20 ms age rule fired {(gap_at - tk) * 1e3:.1f} ms after the kill" if gap_at else
              "  age rule never fired")
        if raised_at:
            print(f"  driver raised {type(err).__name__} {(raised_at - tk) * 1e3:.1f} ms after the kill: {err}"
                  f" (cause {type(err.__cause__).__name__ if err.__cause__ else None})")
    finally:
        srv.kill()
    srv = FciServer(host)
    try:
        c0 = time.monotonic()
        robot.reconnect()  # the same driver, a new franky.Robot
        print(f"  new franky-sim up in {srv.startup_s:.1f} s; reconnect() (a new franky.Robot) took "
              f"{(time.monotonic() - c0) * 1e3:.0f} ms; state seq {robot.state().seq}")
        robot.close()
    finally:
        srv.kill()


def cross_check(host: str, kin: PandaKinematics, dt: float) -> None:
    """Controller's flange pose vs our FK, at rest after point-to-point moves to random postures."""
    with FrankaRobot(kin, host, control_period=dt) as robot:
        rng = np.random.default_rng(7)
        vs_q, vs_qd, lagq = [], [], []
        for _ in range(5):
            goal = np.clip(Q_START + rng.uniform(-0.4, 0.4, 7), kin.q_min + 0.1, kin.q_max - 0.1)
            go_to(robot, kin, goal, dt)
            time.sleep(0.5)
            st = robot.state()
            T_rep = robot.reported_T_base_flange()
            vs_q.append(pose_error(T_rep, st.T_base_flange))
            vs_qd.append(pose_error(T_rep, kin.fk(np.array(robot._raw.q_d), "flange")))
            lagq.append(np.abs(np.array(robot._raw.q_d) - st.q).max())
        print("\nflange pose, controller (O_T_EE * F_T_EE^-1) vs our FK, 5 random postures at rest:")
        for name, errs in (("FK(q_d), the desired joints", vs_qd), ("FK(q), the measured joints", vs_q)):
            print(f"  vs {name:<28} max {max(e[0] for e in errs) * 1e3:.4f} mm, "
                  f"{math.degrees(max(e[1] for e in errs)):.5f} deg")
        print(f"  (|q_d - q| at rest up to {max(lagq) * 1e3:.2f} mrad)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--host", default="127.0.0.60")
    ap.add_argument("--arc-deg", type=float, default=8.0)
    ap.add_argument("--quick", action="store_true", help="only the chosen scheme and the baseline")
    ap.add_argument("--brakes", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=2, help="runs per scheme (franky-sim's pace varies with load)")
    a = ap.parse_args()
    kin = PandaKinematics(T_flange_cam=T_FLANGE_CAM, arm="fr3")
    base = [
        dict(dt=0.001, command_mode="position", send_period=0.001),
        dict(dt=0.004, command_mode="position", send_period=0.004),
        dict(dt=0.001, command_mode="position", send_period=0.01),
        dict(dt=0.004, command_mode="position_velocity", send_period=0.004),
        dict(dt=0.001, command_mode="position_velocity", send_period=0.01),
        dict(dt=0.001, command_mode="impedance", send_period=0.001, gain=0.0,
             stiffness=np.array([600.0, 600.0, 600.0, 600.0, 250.0, 150.0, 50.0])),
    ]
    vel = [dict(dt=dt, command_mode="velocity", send_period=sp, gain=g)
           for dt, sp, g in [(0.001, 0.01, 50.0), (0.004, 0.01, 50.0), (0.004, 0.004, 50.0), (0.001, 0.004, 50.0),
                             (0.001, 0.02, 25.0), (0.001, 0.01, 25.0), (0.001, 0.01, 80.0), (0.001, 0.001, 20.0)]]
    schemes = [base[0], vel[0]] if a.quick else base + vel
    with FciServer(a.host) as srv:
        print(f"franky-sim on {a.host} ready in {srv.startup_s:.1f} s; arc {a.arc_deg} deg")
        scheme_runs(a.host, kin, schemes, a.arc_deg * DEG, a.repeats)
        braking(a.host, kin, 0.001, a.brakes)
        cross_check(a.host, kin, 0.001)
        idle_reads(a.host, kin)
    link_loss(a.host, kin, 0.001)
    rest_link_loss(a.host, kin)
    return 0


if __name__ == "__main__":
    sys.exit(main())
