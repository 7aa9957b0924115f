"""The dry-run: the whole supervisor on the simulated Panda and the synthetic camera.

Sequence, as on the real robot: move to the scene's start view, record the two
model images 2 cm apart, build the target model, return to the start view, then
run one gated arc with the configured stage. Afterwards an *oracle sweep*
(rendered frames along the full arc, localized with the same model, compared
with ground truth) gives the actual envelope boundary the halt is judged
against (`oracle.csv`: each position's mean errors, and its median frame's). Outputs: `summary.json`, `events.jsonl`, `timeline.png`,
`oracle.csv`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.robot.sim import SimRobotDriver
from sim.renderer import Renderer
from sim.robot import SimRobot
from sim.scene import load_scene
from supervisor.arm.kinematics import PandaKinematics
from supervisor.clock import SimClock
from supervisor.config import Config
from supervisor.errors import ConfigError
from supervisor.evaluation.metrics import actual_boundary, first_exceeded
from supervisor.geometry import pose_error
from supervisor.localization.artifacts import viewing_angle
from supervisor.localization.localizer import Localizer, predict_target_pose
from supervisor.localization.model import BoxROI, TargetModel
from supervisor.motion.paths import ArcPath, start_camera_pose
from supervisor.outputs import write_atomic
from supervisor.runtime.builder import Drivers, Supervisor, open_drivers
from supervisor.runtime.events import EventLog
from supervisor.runtime.loop import RunRecord, executed_angles, overshoot
from supervisor.stages import StageConfig

TOLERANCES = {"2mm_3deg": (0.002, math.radians(3.0)), "4mm_10deg": (0.004, math.radians(10.0))}
ORACLE_STEP = math.radians(2.25)
ORACLE_FRAMES = 3
ORACLE_REFINE = 3  # the step before the first exceeded position is sampled again this many times finer


@dataclass(frozen=True)
class DryRunSpec:
    stage: str
    azimuth: float  # rad
    sampling: str | None = None  # override the stage's sampling mode
    scene: str | None = None
    seed: int = 0
    oracle: bool = True
    sweep: float | None = None  # rad; the arc ends here (default: the stage's hard limit)
    accept_reachable: bool = False  # an arc the arm cannot complete: run its reachable part (else refused)
    # The oracle's resolution: where the judged boundary falls between its positions is interpolated, and at
    # 8-12 inliers a frame's pose is fine or grossly wrong by its noise, so a finer step with more frames
    # judges such a cliff more closely (at the cost of rendering and localizing them).
    # The boundary lies in the step before the first position beyond a tolerance; `oracle_refine` samples
    # that step again `oracle_refine` times finer (1: not at all), at each tolerance the run is judged at.
    oracle_step: float = ORACLE_STEP  # rad
    oracle_frames: int = ORACLE_FRAMES
    oracle_refine: int = ORACLE_REFINE
    # s; each result reaches the loop this long after capture (None: its measured compute time, which follows
    # the machine's load). A fixed latency makes a simulated run bit-reproducible: two settings compared on the
    # same renders then differ by the setting alone.
    latency: float | None = None

    def __post_init__(self) -> None:
        if self.latency is not None and not (math.isfinite(self.latency) and 0.0 <= self.latency <= 10.0):
            raise ValueError(f"fixed latency must be in [0, 10000] ms, got {self.latency * 1000:g}")
        if not (math.isfinite(self.oracle_step) and 0 < self.oracle_step <= math.radians(45.0)):
            raise ValueError(f"oracle step must be in (0, 45] deg, got {math.degrees(self.oracle_step):g}")
        if isinstance(self.oracle_frames, bool) or not isinstance(self.oracle_frames, int) or self.oracle_frames < 1:
            raise ValueError(f"oracle frames must be an integer >= 1, got {self.oracle_frames!r}")
        if isinstance(self.oracle_refine, bool) or not isinstance(self.oracle_refine, int) or self.oracle_refine < 1:
            raise ValueError(f"oracle refine must be an integer >= 1, got {self.oracle_refine!r}")


def load_motion(path: str | Path) -> dict[str, Any]:
    """A dry-run motion file -> {"azimuth": rad, "scene": name or None, "sweep": rad or None}.

        kind: arc            # the gated motion (arc only)
        azimuth_deg: 90      # direction of the arc: 0 up, 90 right, 270 left
        scene: phantom       # optional: a name in config/scenes/ or a scene YAML path
        sweep_deg: 30        # optional: end of the arc (capped by the stage's hard limit)
    """
    from supervisor.yamlschema import Node, load_yaml

    node = Node(load_yaml(path), path)
    node.string("kind", "arc", choices=("arc",))
    sweep_deg = node.optional_number("sweep_deg", min=0.0, max=180.0, min_exclusive=True)
    out = {"azimuth": math.radians(node.number("azimuth_deg", min=0.0, max=360.0)),
           "scene": node.optional_string("scene"),
           "sweep": None if sweep_deg is None else math.radians(sweep_deg)}
    node.done()  # the unknown-key hint lists every key above, sweep_deg included
    return out


def run_dry_run(cfg: Config, spec: DryRunSpec, out: Path | None, progress=print, *,
                realtime: bool = False, latency_scale: float = 1.0) -> dict[str, Any]:
    """Run one dry-run trial; write its outputs to `out` (if given) and return the summary.

    In simulated time by default; `realtime` runs the same loop on the wall clock (capture thread,
    localization threads, paced ticks), as the daemon does. In simulated time a result reaches the
    loop its measured compute time (times `latency_scale`) after capture, so a loaded machine sees
    later results, as the real loop would; `latency_scale=0` releases them at capture time, which
    makes the run independent of the machine's load (bit-reproducible).
    """
    wall0 = time.monotonic()
    _require_sim(cfg)
    if realtime and spec.latency is not None:
        raise ValueError("a fixed latency is for simulated time: on the real clock results come when they are ready")
    stage: StageConfig = cfg.stage(spec.stage)
    if spec.sampling is not None:
        stage = dataclasses.replace(stage, sampling=spec.sampling)
    scene = load_scene(spec.scene or cfg.scene)
    pivot_base = (scene.T_base_scene @ np.append(scene.pivot, 1.0))[:3]
    T_base_cam0 = start_camera_pose(pivot_base, scene.view.radius, scene.view.elevation, scene.view.heading)

    progress(f"dry-run: scene {scene.name}, stage {stage.name} ({stage.sampling}, n_t={stage.n_t}, "
             f"step {math.degrees(stage.step):.2f} deg), azimuth {math.degrees(spec.azimuth):g} deg"
             + (" (real time)" if realtime else ""))
    drivers = open_drivers(cfg, realtime=realtime, scene=scene, seed=spec.seed)
    events = EventLog(None if out is None else out / "events.jsonl")
    sup = Supervisor(cfg, drivers, events, stage=stage, latency_scale=latency_scale, latency=spec.latency)
    try:
        events.emit(drivers.clock.now(), "config", sha256=cfg.sha256, file=str(cfg.file), stage=stage.name)
        T_target_box, half = scene.target_box_in_target()
        model = sup.capture_model(T_base_cam0, BoxROI(T_target_box, half), board=scene.board)
        progress(f"  target model: {model.n_features} features, frame={model.frame}")
        plan = sup.plan_arc(pivot_base, spec.azimuth, spec.sweep, accept_reachable=spec.accept_reachable)
        if plan.s_end < (spec.sweep or stage.hard_limit) - 1e-9:
            progress(f"  the arc is shortened to its reachable part, 0-{math.degrees(plan.s_end):.2f} deg")
        if plan.start_changed:
            progress("  the arc starts from another configuration of the arm (the present one cannot complete it)")
            sup.move_to_arc_start(plan)
        record = sup.run(plan)
    finally:
        sup.close()
        events.close()
        drivers.close()
    T0 = sup.T_base_cam_model
    executed_theta = _report_run(record, drivers, T0, progress)
    # The oracle localizes with the model the loop ended with (refined from the robot's motion if enabled).
    renderer = Renderer(scene, cfg.camera.intrinsics) if realtime else drivers.camera.renderer
    _, tol_t, tol_r = judged_tolerance(stage)
    oracle = _oracle(cfg, renderer, sup.final_model, plan.path, T0, stage.hard_limit, spec.seed,
                     scene.reference_point_in_target(), spec.oracle_step, spec.oracle_frames, spec.oracle_refine,
                     [*TOLERANCES.values(), (tol_t, tol_r)]) if spec.oracle else None
    summary = _summary(cfg, stage, scene.name, spec, record, executed_theta, oracle, events, drivers.clock.now(),
                       time.monotonic() - wall0, realtime)
    if realtime and sup.last_pacer is not None:
        summary["ticks"] = sup.last_pacer.stats.summary()
    _write_outputs(out, summary, record, oracle)
    return summary


def _require_sim(cfg: Config) -> None:
    # A dry-run (or replay) is simulation by definition: never let a hardware config silently run on the
    # sim, and never let recorded frames stand in for a live camera on a real robot.
    if cfg.robot.driver != "sim" or cfg.camera.driver != "sim":
        raise ConfigError(Path(cfg.file), "robot.driver" if cfg.robot.driver != "sim" else "camera.driver",
                          "the dry-run needs the sim robot and sim camera; this config selects "
                          f"robot '{cfg.robot.driver}', camera '{cfg.camera.driver}'")


def _report_run(record: RunRecord, drivers: Drivers, T0: np.ndarray, progress) -> np.ndarray:
    """Print the halt; the executed viewing angles, measured on what the robot executed (its state
    after every command), not on the plan."""
    progress(f"  halted at {math.degrees(record.halt_s):.2f} deg ({record.halt_reason}) after "
             f"{drivers.clock.now():.1f} s {'on the clock' if drivers.realtime else 'simulated'}")
    kin = drivers.kin
    return executed_angles(record, kin, T0)


def _write_outputs(out: Path | None, summary: dict[str, Any], record: RunRecord, oracle) -> None:
    if out is None:
        return
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "summary.json", json.dumps(summary, indent=2, sort_keys=True).encode())
    if oracle is not None:  # the judge's evidence: each position's mean (and median) errors (refined: sampled again)
        refined = oracle.get("refined") or [False] * len(oracle["theta"])
        count = len(oracle["theta"])
        t_med, r_med = (oracle.get(k) or [math.nan] * count for k in ("t_err_median", "r_err_median"))
        rows = ["theta_deg,t_err_mm,r_err_deg,n_inliers_mean,refined,t_err_median_mm,r_err_median_deg"]
        rows += [f"{math.degrees(th):.4f},{1000 * te:.4f},{math.degrees(re):.4f},{n:.2f},{int(f)},"
                 f"{1000 * tm:.4f},{math.degrees(rm):.4f}"
                 for th, te, re, n, f, tm, rm in zip(oracle["theta"], oracle["t_err"], oracle["r_err"],
                                                     oracle["n_mean"], refined, t_med, r_med)]
        write_atomic(out / "oracle.csv", ("\n".join(rows) + "\n").encode())
    from supervisor.runtime.plots import plot_timeline

    plot_timeline(record, oracle, summary, out / "timeline.png")


def run_replay(cfg: Config, dataset: str | Path, stage_name: str, out: Path | None, progress=print) -> dict[str, Any]:
    """Replay a recorded stop-and-go arc through the same supervisor loop.

    The sim robot drives the recorded arc (the dataset's start pose, pivot and azimuth) under the
    gate; the camera is the recording itself, serving at each position the images taken there
    (`PoseReplayCamera`). The stage's step and frames per step become the recording's, its
    sampling stop-and-go (nothing was recorded between positions) and its hard limit at most the
    recorded sweep. The actual boundary comes from localizing every recorded frame against the
    recording's ground truth, as `supervisor evaluate` does.
    """
    from drivers.camera.replay import PoseReplayCamera
    from supervisor.dataset.format import Dataset
    from supervisor.errors import DatasetError
    from supervisor.localization.offline import localize_dataset, model_from_dataset, per_position

    wall0 = time.monotonic()
    _require_sim(cfg)
    ds = Dataset.open(dataset)
    meta_file = ds.root / "dataset.json"
    if ds.kind != "arc":
        raise DatasetError(meta_file, f"replay needs an arc recording (the gated motion is an arc), got {ds.kind!r}")
    motion = ds.meta.get("motion") or {}
    try:
        T0 = np.asarray(motion["T_base_cam0"], float).reshape(4, 4)
        pivot = np.asarray(motion["pivot_base"], float).reshape(3)
        azimuth, step = float(motion["azimuth"]), float(motion["step"])
        positions, per_pos = int(motion["positions"]), int(motion["images_per_position"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(meta_file, f"motion: replay needs T_base_cam0, pivot_base, azimuth, step, positions "
                                      f"and images_per_position ({exc!r})") from exc
    stage = cfg.stage(stage_name)
    stage = dataclasses.replace(stage, sampling="stop_and_go", step=step, frames_per_step=per_pos,
                                hard_limit=min(stage.hard_limit, step * (positions - 1) + 1e-9))
    progress(f"replay: {ds.root} ({positions} positions, {per_pos} images each, step "
             f"{math.degrees(step):.2f} deg), stage {stage.name} (n_t={stage.n_t})")
    model = model_from_dataset(ds, cfg.localization)
    progress(f"  target model: {model.n_features} features, frame={model.frame}")

    clock = SimClock()
    kin = PandaKinematics(T_flange_cam=ds.T_flange_cam, urdf=cfg.robot.urdf)
    sim = SimRobot(kin, cfg.robot.q_start, dt=cfg.robot.control_period_s, clock=clock)
    robot = SimRobotDriver(sim)
    camera = PoseReplayCamera(ds, lambda: robot.state().T_base_flange @ ds.T_flange_cam, clock,
                              cfg.camera.frame_period_s)
    drivers = Drivers(robot, camera, kin, clock, realtime=False)
    events = EventLog(None if out is None else out / "events.jsonl")
    sup = Supervisor(cfg, drivers, events, stage=stage)
    try:
        events.emit(clock.now(), "config", sha256=cfg.sha256, file=str(cfg.file), stage=stage.name)
        sup.move_camera_to(ArcPath(T0, pivot, azimuth).pose(0.0))
        sup.use_model(model, T0)
        plan = sup.plan_arc(pivot, azimuth)
        sup.move_to_arc_start(plan)
        record = sup.run(plan)
    finally:
        sup.close()
        events.close()
        drivers.close()
    executed_theta = _report_run(record, drivers, T0, progress)
    # The actual boundary below localizes the recording itself (refining the model the same way).
    oracle = None
    if ds.has_ground_truth:
        rows = localize_dataset(ds, model, cfg.localization)
        pos = per_position(rows, "theta")
        oracle = _oracle_record([float(p["var"]) for p in pos], [float(p["t_err_mean"]) for p in pos],
                                [float(p["r_err_mean"]) for p in pos], [p["n_mean"] for p in pos])
    spec = DryRunSpec(stage=stage.name, azimuth=azimuth, sampling="stop_and_go", seed=int(ds.meta.get("seed", 0)))
    summary = _summary(cfg, stage, str((ds.meta.get("scene") or {}).get("name", ds.name)), spec, record,
                       executed_theta, oracle, events, clock.now(), time.monotonic() - wall0, False)
    summary["replay"] = str(ds.root)
    _write_outputs(out, summary, record, oracle)
    return summary


def oracle_positions(s_max: float, step: float = ORACLE_STEP) -> np.ndarray:
    """Where the oracle localizes (SI): every `step` from 0, and `s_max` when it is not one of them."""
    n = int(math.floor(s_max / step + 1e-9)) + 1
    s = np.arange(n) * step
    return s if s_max - s[-1] <= 1e-9 else np.append(s, s_max)


def judged_tolerance(stage) -> tuple[str, float, float]:
    """The tolerance a run is judged at (name, m, rad): the stage's own when it names one, else 4 mm/10 deg."""
    if stage.tolerance_t is not None and stage.tolerance_r is not None:
        t, r = stage.tolerance_t, stage.tolerance_r
        return f"{t * 1000:g}mm_{math.degrees(r):g}deg", t, r
    return "4mm_10deg", *TOLERANCES["4mm_10deg"]


def refine_positions(s: np.ndarray, t_err: np.ndarray, r_err: np.ndarray,
                     tolerances: list[tuple[float, float]], refine: int) -> list[float]:
    """Where the oracle samples again (SI, ascending): for each tolerance, `refine - 1` evenly spaced positions
    inside the step before its first exceeded position (`s` ascending). Between two positions the boundary is
    only interpolated; at a cliff (a pose 0.5 mm off, then 6.7 mm a step later) the interpolation can sit a
    degree or more from where the error actually crosses, either side of it."""
    out: set[float] = set()
    for tol_t, tol_r in tolerances if refine > 1 else ():
        k = first_exceeded(t_err, r_err, tol_t, tol_r)
        if k:  # None: never exceeded; 0: exceeded at the start, nothing before it
            a, b = float(s[k - 1]), float(s[k])
            out.update(a + j * (b - a) / refine for j in range(1, refine))
    return sorted(out)


def _oracle(cfg: Config, renderer: Renderer, model: TargetModel, path: ArcPath, T0: np.ndarray, s_max: float,
            seed: int, reference_point: np.ndarray, step: float = ORACLE_STEP, frames: int = ORACLE_FRAMES,
            refine: int = 1, tolerances: list[tuple[float, float]] | None = None) -> dict[str, Any]:
    """Per-position mean localization errors over `frames` frames along the whole arc (ground truth from the
    renderer; translation error at the target's reference point): every `step`, and the arc's end `s_max`
    itself (`cut`'s 30 deg is no multiple of 2.25 deg: without it a boundary never reached would read
    as 29.25 deg, and a halt at the hard limit as an incursion); then the step before each of `tolerances`'
    first exceeded position again, `refine` times finer (refine_positions)."""
    loc = Localizer(model, cfg.localization)

    def measure(s: float, first_frame: int) -> tuple[float, float, float, float, float, float]:
        T = path.pose(s)
        te, re, ns = [], [], []
        for i in range(frames):
            fr = renderer.render(T, frame_index=first_frame + i, noise_seed=seed + 7)
            res = loc.localize(fr.image, predict_target_pose(T, T0, model.T_cam0_target))
            ns.append(res.n_inliers)
            if res.ok:
                e_t, e_r = pose_error(res.T_cam_target, fr.T_cam_target, reference_point)
            else:
                e_t, e_r = math.inf, math.inf  # a failed localization exceeds every tolerance
            te.append(e_t)
            re.append(e_r)
        return (viewing_angle(T0, T), float(np.mean(te)), float(np.mean(re)), float(np.mean(ns)),
                float(np.median(te)), float(np.median(re)))

    coarse = oracle_positions(s_max, step)
    rows = [(float(s), *measure(s, 100_000 + k * frames), False) for k, s in enumerate(coarse)]
    extra = refine_positions(coarse, np.array([r[2] for r in rows]), np.array([r[3] for r in rows]),
                             list(tolerances or TOLERANCES.values()), refine)
    for s in extra:  # frames of their own: slot j of the step after coarse position k
        k = int(np.searchsorted(coarse, s)) - 1
        j = round((s - coarse[k]) * refine / (coarse[k + 1] - coarse[k]))
        rows.append((s, *measure(s, 300_000 + (k * refine + j) * frames), True))
    rows.sort(key=lambda r: r[0])
    _, thetas, t_errs, r_errs, n_mean, t_med, r_med, refined = (list(c) for c in zip(*rows))
    return {**_oracle_record(thetas, t_errs, r_errs, n_mean), "step": step, "frames": frames, "refine": refine,
            "refined": refined, "t_err_median": t_med, "r_err_median": r_med}


def _oracle_record(theta: list[float], t_err: list[float], r_err: list[float], n_mean: list[float]) -> dict[str, Any]:
    """The oracle's per-position errors and, from them, the actual boundary at each standard tolerance."""
    th, te, re = np.array(theta), np.array(t_err), np.array(r_err)
    return {"theta": theta, "t_err": t_err, "r_err": r_err, "n_mean": n_mean,
            "boundary": {name: actual_boundary(th, te, re, tt, tr) for name, (tt, tr) in TOLERANCES.items()}}


def _verdict(theta: np.ndarray, t_err: np.ndarray, r_err: np.ndarray, tol_t: float, tol_r: float, halt: float,
             max_exec: float, lost: str = "at") -> tuple[float, bool, float | None]:
    a = actual_boundary(theta, t_err, r_err, tol_t, tol_r, lost=lost)
    return a, bool(max_exec > a + 1e-9), float(halt / a) if a > 0 else None


def verdicts(oracle: dict[str, Any], tol_t: float, tol_r: float, halt: float, max_exec: float) -> dict[str, Any]:
    """A run judged at one tolerance (m, rad; angles SI in, degrees out): the actual boundary, incursion (the arm
    executed past it) and envelope usage (the halt over it), from every position the oracle sampled. Beside it:
    - `coarse_judge`, when the oracle refined a step: the same from its coarse positions alone;
    - `strict_judge`: where the first position beyond the tolerance lost a frame there is no error to interpolate
      toward, and the judge puts the boundary at that position (the latest the error can have crossed); the
      strict reading puts it at the position before (the earliest). A halt between the two is judged safe by the
      one and an incursion by the other: the oracle's frames cannot tell which (a finer oracle may);
    - `majority_judge`, when the oracle recorded it: the same from each position's median frame error instead of the
      mean, so a position fails when most of its frames do, not when one of them is lost or gross (the judge's own
      noise: docs/tuning.md, session 29). A reading beside the judge, never instead of it."""
    theta, t_err, r_err = (np.asarray(oracle[k], float) for k in ("theta", "t_err", "r_err"))
    a, inc, usage = _verdict(theta, t_err, r_err, tol_t, tol_r, halt, max_exec)
    out: dict[str, Any] = {"actual_boundary_judged_deg": math.degrees(a), "incursion": inc, "envelope_usage": usage}
    if any(oracle.get("refined") or ()):
        keep = ~np.asarray(oracle["refined"], bool)
        c, c_inc, c_usage = _verdict(theta[keep], t_err[keep], r_err[keep], tol_t, tol_r, halt, max_exec)
        out["coarse_judge"] = {"actual_boundary_deg": math.degrees(c), "incursion": c_inc, "envelope_usage": c_usage}
    s, s_inc, s_usage = _verdict(theta, t_err, r_err, tol_t, tol_r, halt, max_exec, lost="last_good")
    out["strict_judge"] = {"actual_boundary_deg": math.degrees(s), "incursion": s_inc, "envelope_usage": s_usage}
    if oracle.get("t_err_median") is not None:
        t_med, r_med = (np.asarray(oracle[k], float) for k in ("t_err_median", "r_err_median"))
        m, m_inc, m_usage = _verdict(theta, t_med, r_med, tol_t, tol_r, halt, max_exec)
        out["majority_judge"] = {"actual_boundary_deg": math.degrees(m), "incursion": m_inc, "envelope_usage": m_usage}
    return out


def _summary(cfg, stage, scene_name: str, spec, record: RunRecord, executed_theta: np.ndarray, oracle,
             events: EventLog, clock_time: float, wall_time: float, realtime: bool) -> dict[str, Any]:
    halt = record.halt_s
    theta_p = [p for _, p, _ in record.theta_p_history if math.isfinite(p)]
    allowed = record.s_allowed_at_brake
    max_exec = float(executed_theta.max()) if len(executed_theta) else 0.0
    over, shortfall = overshoot(np.asarray(record.trajectory_t), executed_theta, record.allowance_history)
    out: dict[str, Any] = {
        "stage": stage.name, "sampling": stage.sampling, "predictor": stage.predictor, "variant": stage.variant,
        "n_t": stage.n_t, "step_deg": math.degrees(stage.step), "margin_deg": math.degrees(stage.margin),
        "final_step": stage.final_step, "final_step_clearance_deg": math.degrees(stage.final_step_clearance),
        "scene": scene_name, "azimuth_deg": math.degrees(spec.azimuth), "seed": spec.seed,
        "config_sha256": cfg.sha256, "halt_reason": record.halt_reason,
        "halt_angle_deg": math.degrees(halt),
        "max_executed_angle_deg": math.degrees(max_exec),
        "predicted_boundary_deg": math.degrees(theta_p[-1]) if theta_p else None,
        "theta_allowed_at_brake_deg": math.degrees(allowed) if math.isfinite(allowed) else None,
        # Executed angle beyond the allowance in force at each tick (see runtime.loop.overshoot);
        # the final-allowance comparison and the revision shortfall are reported beside it.
        "max_overshoot_deg": math.degrees(over) if math.isfinite(over) else None,
        "overshoot_of_final_allowance_deg": math.degrees(max_exec - allowed) if math.isfinite(allowed) else None,
        "revision_shortfall_deg": math.degrees(shortfall),
        "n_samples": len(record.samples), "n_predictions": len(record.theta_p_history),
        "consistency_limit_mm": stage.consistency_t * 1000, "consistency_limit_deg": math.degrees(stage.consistency_r),
        "worst_frame_limit_mm": stage.worst_frame_t * 1000, "worst_frame_limit_deg": math.degrees(stage.worst_frame_r),
        "min_inlier_ratio": stage.min_inlier_ratio, "inlier_ratio_frames": stage.inlier_ratio_frames,
        "error_kappa": stage.error_kappa,  # None: no error bound
        "max_consistency_drift_mm": 1000 * max((c[2] for c in record.consistency), default=0.0),
        "max_consistency_drift_deg": math.degrees(max((c[3] for c in record.consistency), default=0.0)),
        "faults": [e["fault"] for e in events.of_kind("fault")],
        # null: each result came its measured compute time after capture (the machine's load shows)
        "fixed_latency_ms": None if getattr(spec, "latency", None) is None else spec.latency * 1000,
        "wall_time_s": wall_time,
        **({"realtime": True} if realtime else {"simulated_time_s": clock_time}),
    }
    if oracle is not None:
        if "step" in oracle:  # a rendered oracle (a replay's is the recording's own positions)
            out["oracle_step_deg"], out["oracle_frames"] = math.degrees(oracle["step"]), oracle["frames"]
            out["oracle_refine"] = oracle["refine"]
        out["actual_boundary_deg"] = {k: math.degrees(v) for k, v in oracle["boundary"].items()}
        out["incursion_by_tolerance"] = {k: bool(max_exec > v + 1e-9) for k, v in oracle["boundary"].items()}
        name, tol_t, tol_r = judged_tolerance(stage)
        out["judged_tolerance"] = name
        out.update(verdicts(oracle, tol_t, tol_r, halt, max_exec))
    return out

