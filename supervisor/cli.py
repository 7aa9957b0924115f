"""Command-line interface: `supervisor <command> ...`.

Errors the user can fix (bad config, bad dataset, unknown scene or driver)
print one line naming the file and the problem and exit with status 2.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

from supervisor.errors import SupervisorError

EXIT_USAGE = 2


def _config(args: argparse.Namespace):
    from supervisor.config import load_config

    return load_config(args.config)


def _finite(text: str) -> float:
    """argparse type: a finite number (nan/inf are refused naming the flag)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def _latency_ms(text: str) -> float:
    """argparse type: a fixed localization latency in ms, 0 to 10000."""
    value = _finite(text)
    if not 0.0 <= value <= 10000.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 10000] ms, got {text!r}")
    return value


def cmd_dataset_generate(args: argparse.Namespace) -> int:
    from sim.scene import load_scene
    from supervisor.dataset.format import DATASET_COMMAND, DATASET_FILES
    from supervisor.outputs import check_target

    check_target(args.out, DATASET_COMMAND, replace=args.force, known=DATASET_FILES,
                 exists_hint="choose another path, or --force to replace a dataset")
    cfg = _config(args)
    scene = load_scene(args.scene or cfg.scene)  # an unknown scene fails here, before any robot code loads
    from supervisor.dataset.generate import ArcSpec, LineSpec, generate_arc, generate_line

    t0 = time.monotonic()
    if args.motion == "arc":
        out = generate_arc(cfg, args.out, ArcSpec(math.radians(args.azimuth), args.images_per_position),
                           scene, args.seed, overwrite=args.force)
    else:
        out = generate_line(cfg, args.out, LineSpec(math.radians(args.offset), args.images_per_position),
                            scene, args.seed, overwrite=args.force)
    print(f"wrote dataset {out} in {time.monotonic() - t0:.1f} s")
    return 0


def cmd_benchmark_generate(args: argparse.Namespace) -> int:
    from supervisor.dataset.benchmark import generate_suite

    cfg = _config(args)
    t0 = time.monotonic()
    arc_step = None
    if args.step_deg is not None:
        sweep = math.degrees(cfg.dataset.arc.sweep)
        if not 0 < args.step_deg <= sweep:
            raise SupervisorError(f"benchmark generate: --step-deg must be in (0, {sweep:g}] deg (the arc's sweep, "
                                  f"dataset.arc.sweep_deg), got {args.step_deg:g}")
        arc_step = math.radians(args.step_deg)
    out = generate_suite(cfg, args.out, quick=args.quick, jobs=args.jobs, seed=args.seed, suite=args.suite,
                         arc_step=arc_step)
    print(f"benchmark suite ready in {out} ({time.monotonic() - t0:.0f} s)")
    return 0


def cmd_model_build(args: argparse.Namespace) -> int:
    from supervisor.dataset.format import Dataset
    from supervisor.errors import ModelFormatError, OutputError
    from supervisor.localization.model import TargetModel
    from supervisor.localization.offline import model_from_dataset
    from supervisor.outputs import check_location, record_file

    out = check_location(args.output or Path(args.dataset) / "model.npz", directory=False)
    if out.exists():
        try:
            TargetModel.load(out)
        except ModelFormatError:
            raise OutputError(out, "exists and is not a target model; it is never overwritten") from None
    cfg = _config(args)
    ds = Dataset.open(args.dataset)
    model = model_from_dataset(ds, cfg.localization)
    model.save(out)
    if not args.output:
        record_file(out.parent, out.name)
    print(f"wrote target model {out}: {len(model.points_target)} features, frame={model.frame}")
    return 0


def cmd_localize(args: argparse.Namespace) -> int:
    from supervisor.dataset.format import Dataset
    from supervisor.localization.model import TargetModel
    from supervisor.outputs import StagedOutput

    with StagedOutput(args.out, "localize", known=LOCALIZE_FILES) as staged:
        cfg = _config(args)
        ds = Dataset.open(args.dataset)
        model = TargetModel.load(args.model) if args.model else None
        _localize_and_report(ds, model, cfg, staged.path, roi=args.roi)
    print(f"wrote {staged.final / LOCALIZE_FILES[0]} and {staged.final / LOCALIZE_FILES[1]}")
    return 0


LOCALIZE_FILES = ("localization.csv", "localization.png")


def _localize_and_report(ds, model, cfg, out: Path, roi: str | None = None) -> None:
    import dataclasses

    from supervisor.localization import offline
    from supervisor.outputs import write_atomic

    settings = cfg.localization if roi is None else dataclasses.replace(cfg.localization, roi=roi)
    if model is None:
        t0 = time.monotonic()
        model = offline.model_from_dataset(ds, settings)
        print(f"built target model: {len(model.points_target)} features in {time.monotonic() - t0:.1f} s",
              file=sys.stderr)
    rows = offline.localize_dataset(ds, model, settings, offline.print_progress)
    write_atomic(out / "localization.csv", offline.artifacts_csv(rows))
    write_atomic(out / "localization.png",
                 offline.plot_artifacts(rows, ds.kind, f"{ds.name}: n_i and error vs motion"))
    print(offline.format_table(rows, ds.kind))


def cmd_demo(args: argparse.Namespace) -> int:
    """Main job until the dry-run lands: a quick arc dataset, localized, n_i-vs-angle table."""
    from supervisor.dataset.format import Dataset
    from supervisor.dataset.generate import ArcSpec, generate_arc
    from supervisor.outputs import StagedOutput

    with StagedOutput(args.out, "demo", known=("dataset", *LOCALIZE_FILES)) as staged:
        cfg = _config(args)
        print(f"generating a quick arc dataset ({cfg.scene}, azimuth {args.azimuth:g} deg, "
              f"{args.images_per_position} images per position) in {staged.final / 'dataset'}")
        ds_dir = generate_arc(cfg, staged.path / "dataset", ArcSpec(math.radians(args.azimuth),
                                                                    args.images_per_position), None, 0)
        _localize_and_report(Dataset.open(ds_dir), None, cfg, staged.path)
    print(f"wrote {staged.final / 'dataset'}, {staged.final / LOCALIZE_FILES[0]} and {staged.final / LOCALIZE_FILES[1]}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from supervisor.evaluation.experiments import run_evaluation
    from supervisor.evaluation.report import tables

    cfg = _config(args)
    report = run_evaluation(cfg, args.bench_dir, args.out, jobs=args.jobs or 2)
    print(tables(report))
    print(f"wrote {Path(args.out) / 'results.json'}, tables.md and SPL-vs-incursion plots")
    return 0


def cmd_evolution_fit_guided(args: argparse.Namespace) -> int:
    """Fit the viewpoint evolution's guided model (paper 2, eq. 20) from good linear-schedule runs."""
    import json

    import numpy as np

    from supervisor.dataset.format import Dataset
    from supervisor.localization import offline
    from supervisor.localization.evolution import fit_guided, guided_samples
    from supervisor.outputs import write_atomic

    cfg = _config(args)
    xs, es, n_good, n_runs = [], [], 0, 0
    for path in args.datasets:
        ds = Dataset.open(path)
        model = offline.model_from_dataset(ds, cfg.localization)
        good, total = offline.guided_training_runs(ds, model, cfg.localization, args.every,
                                                   args.tolerance_mm / 1000.0, math.radians(args.tolerance_deg))
        n_good, n_runs = n_good + len(good), n_runs + total
        for run in good:
            x, e = guided_samples(run)
            xs.append(x)
            es.append(e)
        print(f"{ds.name}: {len(good)} good runs of {total}", file=sys.stderr)
    n_samples = sum(len(x) for x in xs)
    if n_samples < 12:
        print(f"error: too few samples from good runs to fit the guided model ({n_samples} < 12)", file=sys.stderr)
        return EXIT_USAGE
    gm = fit_guided(np.concatenate(xs), np.concatenate(es), args.b0, args.p_r)
    meta = dict(gm.meta, good_runs=n_good, runs=n_runs, datasets=[str(p) for p in args.datasets])
    out = Path(args.output)
    write_atomic(out, json.dumps(dict(gm.to_json(), meta=meta), indent=1).encode())
    print(f"wrote guided model {out}: b = {', '.join(f'{v:.2f}' for v in gm.b)} ({n_good} good runs of {n_runs})")
    return 0


def cmd_tune(args: argparse.Namespace) -> int:
    from supervisor.evaluation.tune import format_report, tune

    cfg = _config(args)
    variants = tuple(v for v in args.variants.split(",") if v) if args.variants else None
    out = args.out or f"out/tune-{args.stage}-{args.tolerance}"
    report = tune(cfg, args.bench_dir, args.stage, args.tolerance, out, cache=args.cache, variants=variants,
                  error_aware=args.error_aware, inlier_ratio=args.inlier_ratio, worst_frame=args.worst_frame,
                  strict_boundary=args.strict_boundary, jobs=args.jobs or 2)
    print(format_report(report))
    return 0


def cmd_dry_run(args: argparse.Namespace) -> int:
    """The product's main job: one gated arc on the sim robot with the synthetic camera and the real pipeline."""
    from supervisor.dryrun import DryRunSpec, load_motion, run_dry_run, run_replay
    from supervisor.outputs import StagedOutput, check_target

    if args.fixed_latency_ms is not None and (args.realtime or args.replay):
        print("error: --fixed-latency-ms is for a rendered run in simulated time (not with --realtime or --replay)",
              file=sys.stderr)
        return EXIT_USAGE
    out = check_target(args.out, "dry-run", known=DRY_RUN_FILES)  # before any work; staged below
    cfg = _config(args)
    if args.replay:
        with StagedOutput(out, "dry-run", known=DRY_RUN_FILES) as staged:
            s = run_replay(cfg, args.replay, args.stage or cfg.default_stage, staged.path, print)
    else:
        motion = load_motion(args.motion) if args.motion else {"azimuth": math.radians(90.0), "scene": None,
                                                                "sweep": None}
        # explicit flags override the motion file
        azimuth = math.radians(args.azimuth) if args.azimuth is not None else motion["azimuth"]
        spec = DryRunSpec(stage=args.stage or cfg.default_stage, azimuth=azimuth, sampling=args.sampling,
                          scene=args.scene or motion["scene"], seed=args.seed, oracle=not args.no_oracle,
                          sweep=motion["sweep"], accept_reachable=args.reachable,
                          latency=None if args.fixed_latency_ms is None else args.fixed_latency_ms / 1000.0)
        with StagedOutput(out, "dry-run", known=DRY_RUN_FILES) as staged:
            s = run_dry_run(cfg, spec, staged.path, print, realtime=args.realtime)
    print(f"stage {s['stage']} ({s['sampling']}), scene {s['scene']}, azimuth {s['azimuth_deg']:g} deg: "
          f"halted at {s['halt_angle_deg']:.2f} deg ({s['halt_reason']})")
    if s.get("predicted_boundary_deg") is not None:
        print(f"  predicted boundary theta_p {s['predicted_boundary_deg']:.2f} deg, allowed "
              f"{s['theta_allowed_at_brake_deg']:.2f} deg, max overshoot {s['max_overshoot_deg']:+.3f} deg")
    if "actual_boundary_deg" in s:
        ab = s["actual_boundary_deg"]
        print(f"  actual boundary (ground truth): {ab['4mm_10deg']:.2f} deg at 4 mm/10 deg, "
              f"{ab['2mm_3deg']:.2f} deg at 2 mm/3 deg; at the stage's {s['judged_tolerance']} "
              f"{s['actual_boundary_judged_deg']:.2f} deg: incursion: {'YES' if s['incursion'] else 'no'}; "
              f"envelope usage {100 * s['envelope_usage']:.0f}%")
    print(f"wrote {out / 'summary.json'}, {out / 'events.jsonl'}, {out / 'timeline.png'}"
          + (f", {out / 'oracle.csv'}" if "actual_boundary_deg" in s else ""))
    return 0


def cmd_daemon(args: argparse.Namespace) -> int:
    """Run the supervisor daemon in the foreground (systemd Type=notify)."""
    from supervisor.daemon.client import default_socket
    from supervisor.daemon.server import ControlServer
    from supervisor.daemon.service import Daemon

    sock = Path(args.socket) if args.socket else default_socket()
    log_dir = Path(args.log_dir) if args.log_dir else Path(os.environ.get("LOGS_DIRECTORY", "out/daemon"))
    daemon = Daemon(args.config, log_dir=log_dir)
    daemon.install_signals()
    try:
        server = ControlServer(sock, daemon.handle, group=args.group)
    except BaseException:
        daemon.close()
        raise
    print(f"supervisor daemon: config {daemon.cfg.file} ({daemon.cfg.sha256[:12]}), control socket {sock}, "
          f"logs {log_dir}", flush=True)
    try:
        return daemon.serve()
    finally:
        server.close()


def cmd_ctl(args: argparse.Namespace) -> int:
    """Send one command to the daemon; print its JSON reply; 0 on success, 2 when refused."""
    import json

    from supervisor.daemon.client import default_socket, request

    req: dict = {"cmd": args.ctl}
    timeout = 30.0
    if args.ctl == "run":
        if args.motion:
            from supervisor.dryrun import load_motion

            m = load_motion(args.motion)
            req["azimuth_deg"] = math.degrees(m["azimuth"])
            if m["sweep"] is not None:
                req["sweep_deg"] = math.degrees(m["sweep"])
        else:
            req["azimuth_deg"] = args.azimuth
            if args.sweep is not None:
                req["sweep_deg"] = args.sweep
    elif args.ctl == "wait":
        req["timeout"] = args.timeout
        timeout = args.timeout + 5.0
    elif args.ctl == "stage":
        req["name"] = args.name
    elif args.ctl == "reload":
        if args.file:
            req["file"] = str(Path(args.file).resolve())
    elif args.ctl == "model":
        req["action"] = args.action
        if args.action == "load":
            if not args.file:
                raise SupervisorError("ctl model load needs FILE")
            req["file"] = str(Path(args.file).resolve())
        elif args.depth_mm:
            req["depth_mm"] = args.depth_mm
        timeout = 180.0
    reply = request(Path(args.socket) if args.socket else default_socket(), req, timeout)
    print(json.dumps(reply, indent=2, sort_keys=True))
    return 0 if reply.get("ok") else EXIT_USAGE


def cmd_config(args: argparse.Namespace) -> int:
    from supervisor.configinfo import check_report, show_document

    report = check_report if args.sub == "check" else show_document
    print(report(args.file or args.config).rstrip("\n"))
    return 0


def cmd_can_monitor(args: argparse.Namespace) -> int:
    """Consume the supervisor's heartbeat; 0 when it never tripped, 1 when it did (2: bad input)."""
    from supervisor.can.codec import Codec
    from supervisor.can.channel import open_bus
    from supervisor.can.monitor import HeartbeatMonitor, run_monitor

    cfg = _config(args)
    if cfg.can is None:
        raise SupervisorError(f"{cfg.file}: can: no CAN side channel is configured")
    timeout = cfg.can.consumer_timeout if args.timeout_ms is None else args.timeout_ms / 1000.0
    if not timeout > 0:
        raise SupervisorError(f"--timeout-ms must be > 0, got {args.timeout_ms}")
    bus = open_bus(cfg.can)
    bus.open()
    mon = HeartbeatMonitor(Codec.from_settings(cfg.can), timeout, cfg.can.max_counter_jump,
                           print_fn=lambda text: print(text, flush=True))
    print(f"monitoring {bus.name}, heartbeat id 0x{cfg.can.frames['heartbeat']:x}, timeout {timeout * 1000:.0f} ms",
          flush=True)
    try:
        trip = run_monitor(bus, mon, duration=args.duration)
    except KeyboardInterrupt:
        trip = mon.trip
    finally:
        bus.close()
    print(f"heartbeats {mon.beats}, stops {mon.stops}, rejected {mon.rejected or 0}, "
          f"{'TRIPPED' if trip else 'not tripped'}", flush=True)
    return 1 if trip else 0


DRY_RUN_FILES = ("summary.json", "events.jsonl", "timeline.png", "oracle.csv")


def cmd_calibrate_intrinsics(args: argparse.Namespace) -> int:
    from supervisor.calibration.commands import parse_board, run_intrinsics

    if args.board:
        board = parse_board(args.board)
    else:
        from sim.scene import load_scene

        board = load_scene(args.scene or _config(args).scene).board
    r = run_intrinsics(args.images, board, Path(args.output), fix_k3=not args.free_k3)
    rep = r["report"]
    print(f"{rep['views_used']} views ({len(rep['views_rejected'])} rejected), RMS {rep['rms_px']:.3f} px: "
          f"fx {rep['fx']:.2f} fy {rep['fy']:.2f} cx {rep['cx']:.2f} cy {rep['cy']:.2f} px")
    print("wrote " + ", ".join(r["files"]))
    return 0


def cmd_calibrate_hand_eye(args: argparse.Namespace) -> int:
    from supervisor.calibration.commands import parse_board, run_hand_eye

    r = run_hand_eye(args.datasets, Path(args.output), parse_board(args.board) if args.board else None)
    rep, T = r["report"], r["T_flange_cam"]
    print(f"{rep['views_used']} views, RMS {rep['rms_px']:.3f} px, board spread {rep['board_spread_mm']:.3f} mm / "
          f"{rep['board_spread_deg']:.3f} deg: T_flange_cam translation "
          f"[{', '.join(f'{1000 * v:.2f}' for v in T[:3, 3])}] mm")
    print("wrote " + ", ".join(r["files"]))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="supervisor", description=__doc__.splitlines()[0])
    p.add_argument("--config", default=None, help="configuration YAML (default: embedded config/default.yaml)")
    sub = p.add_subparsers(dest="command", required=True)

    cf = sub.add_parser("config", help="check a configuration file, or show it with what it extends merged in")
    cfs = cf.add_subparsers(dest="sub", required=True)
    for name, text in (("check", "validate FILE (default: --config or the embedded one) and every file it extends; "
                                 "print its stages, robot, camera and SHA-256"),
                       ("show", "print the effective configuration (the extends: chain merged) as YAML")):
        c = cfs.add_parser(name, help=text)
        c.add_argument("file", nargs="?", default=None)
        c.set_defaults(func=cmd_config)

    ds = sub.add_parser("dataset", help="recorded datasets").add_subparsers(dest="sub", required=True)
    g = ds.add_parser("generate", help="record a dataset in simulation (paper protocol)")
    g.add_argument("out")
    g.add_argument("--scene", default=None, help="scene name or YAML path (default: the config's)")
    g.add_argument("--motion", choices=["arc", "line"], required=True)
    g.add_argument("--azimuth", type=_finite, default=0.0, help="arc direction [deg]: 0 up, 90 right, 270 left")
    g.add_argument("--offset", type=_finite, default=0.0, help="line start offset from the model view [deg]")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--images-per-position", type=int, default=None)
    g.add_argument("--force", action="store_true", help="replace an existing output directory")
    g.set_defaults(func=cmd_dataset_generate)

    bm = sub.add_parser("benchmark", help="benchmark suites").add_subparsers(dest="sub", required=True)
    bg = bm.add_parser("generate", help="record the benchmark suite (>= 21 arcs + 4 lines)")
    bg.add_argument("out")
    bg.add_argument("--quick", action="store_true", help="3 images per position instead of 10")
    bg.add_argument("--suite", choices=("v2", "v3"), default="v3",
                    help="v3 (default): every v2 dataset plus the decay-shape scenes; v2: the previous suite exactly")
    bg.add_argument("--jobs", type=int, default=None, help="parallel processes (default: up to 2)")
    bg.add_argument("--seed", type=int, default=0)
    bg.add_argument("--step-deg", type=_finite, default=None,
                    help="the arcs' step instead of the config's dataset.arc.step_deg (2.25): a live stage's step "
                         "(explore: 1.5) makes `tune` replay the steps that stage takes")
    bg.set_defaults(func=cmd_benchmark_generate)

    md = sub.add_parser("model", help="target models").add_subparsers(dest="sub", required=True)
    mb = md.add_parser("build", help="build the target model from a dataset's model images")
    mb.add_argument("dataset")
    mb.add_argument("-o", "--output", default=None, help="output .npz (default: DATASET/model.npz)")
    mb.set_defaults(func=cmd_model_build)

    lo = sub.add_parser("localize", help="localize every frame of a dataset")
    lo.add_argument("dataset")
    lo.add_argument("--model", default=None, help="target model .npz (default: built from the dataset)")
    lo.add_argument("-o", "--out", required=True)
    lo.add_argument("--roi", choices=["predicted", "off"], default=None, help="override localization.roi")
    lo.set_defaults(func=cmd_localize)

    ev = sub.add_parser("evaluate", help="the paper's offline evaluation of every predictor on a benchmark suite")
    ev.add_argument("bench_dir")
    ev.add_argument("-o", "--out", required=True)
    ev.add_argument("--jobs", type=int, default=None, help="parallel processes (default 2)")
    ev.set_defaults(func=cmd_evaluate)

    tu = sub.add_parser("tune", help="a stage's operating point for a tolerance, by leave-one-scene-out "
                                      "cross-validation on a benchmark suite")
    tu.add_argument("bench_dir", nargs="+",
                    help="a benchmark suite, or several recordings of the same scenes (e.g. `benchmark generate "
                         "--seed`): a fold leaves a scene out of every one")
    tu.add_argument("--stage", required=True)
    tu.add_argument("--tolerance", required=True, choices=("2mm_3deg", "4mm_10deg"))
    tu.add_argument("-o", "--out", default=None, help="output directory (default out/tune-STAGE-TOLERANCE)")
    tu.add_argument("--variants", default=None,
                    help="comma-separated model variants to choose among (default: the stage's)")
    tu.add_argument("--error-aware", action="store_true", help="also tune the error-aware boundary's kappa")
    tu.add_argument("--inlier-ratio", action="store_true",
                    help="also tune the inlier-ratio gate's limit (min_inlier_ratio: 0.28, 0.24, 0.2 or off)")
    tu.add_argument("--worst-frame", action="store_true",
                    help="also tune the guard's worst-frame limit (worst_frame_limit_*: 0.625 or 0.75 x the "
                         "tolerance, or off): a position stops the arc when any one frame drifts past it")
    tu.add_argument("--strict-boundary", action="store_true",
                    help="judge stops against boundaries whose crossing toward a position that did not localize "
                         "lies at the last position within tolerance (the earliest it can be), not at the lost "
                         "position (the latest): a dry-run's refined oracle finds such cliffs inside the step")
    tu.add_argument("--cache", action="append", default=None,
                    help="localization cache directory, once per suite in order (default OUT/cache, then "
                         "OUT/cache-2, ...; an `evaluate` OUT/cache can be reused)")
    tu.add_argument("--jobs", type=int, default=None, help="parallel processes (default 2)")
    tu.set_defaults(func=cmd_tune)

    dr = sub.add_parser("dry-run", help="gated arc on the simulated robot with the real pipeline (main job)")
    dr.add_argument("--stage", default=None, help="stage name (default: the config's default_stage)")
    dr.add_argument("--scene", default=None, help="scene name or YAML path (default: the config's)")
    dr.add_argument("--azimuth", type=_finite, default=None,
                    help="arc direction [deg]: 0 up, 90 right, 270 left (default 90, or the motion file's)")
    dr.add_argument("--motion", default=None, metavar="FILE",
                    help="motion YAML: kind: arc, azimuth_deg, optional scene and sweep_deg")
    dr.add_argument("--sampling", choices=["stop_and_go", "continuous"], default=None,
                    help="override the stage's sampling mode")
    dr.add_argument("--seed", type=int, default=0)
    dr.add_argument("--no-oracle", action="store_true", help="skip the ground-truth sweep (no actual boundary)")
    dr.add_argument("--replay", default=None, metavar="DATASET",
                    help="replay a recorded stop-and-go arc through the loop instead of rendering "
                         "(the scene, azimuth and sampling come from the recording)")
    dr.add_argument("--realtime", action="store_true",
                    help="run on the wall clock as the daemon does (capture thread, localization threads, "
                         "paced ticks) instead of simulated time")
    dr.add_argument("--reachable", action="store_true",
                    help="an arc the arm cannot complete runs its reachable part instead of being refused")
    dr.add_argument("--fixed-latency-ms", type=_latency_ms, default=None, metavar="MS",
                    help="each localization result reaches the loop this long after capture (default: its measured "
                         "compute time, which follows the machine's load); the run is then bit-reproducible")
    dr.add_argument("-o", "--out", default="out/dry-run")
    dr.set_defaults(func=cmd_dry_run)

    dm = sub.add_parser("daemon", help="run the supervisor daemon in the foreground (systemd Type=notify)")
    dm.add_argument("--config", default=argparse.SUPPRESS, help="configuration YAML (as before the command)")
    dm.add_argument("--socket", default=None, help="control socket (default: $RUNTIME_DIRECTORY/control.sock)")
    dm.add_argument("--log-dir", default=None, help="event log directory (default: $LOGS_DIRECTORY or out/daemon)")
    dm.add_argument("--group", default=None, help="group allowed on the control socket (mode 0660; default 0600)")
    dm.set_defaults(func=cmd_daemon)

    ct = sub.add_parser("ctl", help="send a command to the running daemon")
    ct.add_argument("--socket", default=None, help="control socket (default: $RUNTIME_DIRECTORY/control.sock)")
    cs = ct.add_subparsers(dest="ctl", required=True)
    for name, text in (("status", "state, stage, faults, last run"), ("arm", "arm (idle -> armed)"),
                       ("rearm", "after a halt: re-check and arm again"), ("stop", "brake now / disarm (always)"),
                       ("shutdown", "brake, flush the logs and exit")):
        cs.add_parser(name, help=text)
    cr = cs.add_parser("run", help="run one gated arc")
    g = cr.add_mutually_exclusive_group(required=True)
    g.add_argument("--azimuth", type=_finite, help="arc direction [deg]")
    g.add_argument("--motion", default=None, metavar="FILE", help="motion YAML (kind: arc, azimuth_deg, sweep_deg)")
    cr.add_argument("--sweep", type=_finite, default=None, help="end of the arc [deg] (default: the stage's hard limit)")
    cw = cs.add_parser("wait", help="wait for the current run to end and print its summary")
    cw.add_argument("--timeout", type=float, default=600.0)
    cg = cs.add_parser("stage", help="switch stage (only at rest)")
    cg.add_argument("name")
    cl = cs.add_parser("reload", help="reload the config (only idle; keeps the last good one on any error)")
    cl.add_argument("file", nargs="?", default=None)
    cm = cs.add_parser("model", help="build the target model (two images 2 cm apart) or load one")
    cm.add_argument("action", choices=["build", "load"])
    cm.add_argument("file", nargs="?", default=None)
    cm.add_argument("--depth-mm", type=float, nargs=2, default=None, metavar=("NEAR", "FAR"),
                    help="the target's depth range (cameras without a known start view)")
    ct.set_defaults(func=cmd_ctl)


    cn = sub.add_parser("can", help="the CAN side channel").add_subparsers(dest="sub", required=True)
    cmon = cn.add_parser("monitor", help="consume the heartbeat; print state changes; exit 1 once it trips")
    cmon.add_argument("--config", default=argparse.SUPPRESS, help="configuration YAML (as before the command)")
    cmon.add_argument("--timeout-ms", type=_finite, default=None, help="consumer timeout (default: can.consumer_timeout_ms)")
    cmon.add_argument("--duration", type=_finite, default=None, help="stop after this many seconds (default: until it trips)")
    cmon.set_defaults(func=cmd_can_monitor)

    ca = sub.add_parser("calibrate", help="camera calibration (ChArUco)").add_subparsers(dest="sub", required=True)
    ci = ca.add_parser("intrinsics", help="intrinsics from ChArUco images -> the config's camera section (YAML)")
    ci.add_argument("images", nargs="+")
    ci.add_argument("-o", "--output", required=True, help="output YAML (also writes .json report and .png plot)")
    ci.add_argument("--board", default=None, help="SXxSY:SQUARE_MM:MARKER_MM:DICT (default: the scene's board)")
    ci.add_argument("--scene", default=None, help="take the board from this scene (default: the config's)")
    ci.add_argument("--free-k3", action="store_true", help="also fit k3 (default: fixed at 0)")
    ci.set_defaults(func=cmd_calibrate_intrinsics)
    ch = ca.add_parser("hand-eye", help="T_flange_cam from recorded flange poses and board poses")
    ch.add_argument("datasets", nargs="+", metavar="DATASET",
                    help="recordings with the board in view; rotate about two axes (e.g. arcs at azimuth 0 and 90)")
    ch.add_argument("-o", "--output", required=True, help="output YAML (also writes .json report and .png plot)")
    ch.add_argument("--board", default=None, help="SXxSY:SQUARE_MM:MARKER_MM:DICT (default: the recording's)")
    ch.set_defaults(func=cmd_calibrate_hand_eye)

    evo = sub.add_parser("evolution", help="viewpoint-evolution refinement (localization.refine: evolution)")
    evs = evo.add_subparsers(dest="sub", required=True)
    fg = evs.add_parser("fit-guided", help="fit the guided model (power-law evolution functions) from good runs")
    fg.add_argument("datasets", nargs="+", help="datasets with ground truth")
    fg.add_argument("-o", "--output", required=True, help="guided-model JSON (localization.evolution.guided_model)")
    fg.add_argument("--every", type=int, default=1, help="use every N-th frame")
    fg.add_argument("--tolerance-mm", type=float, default=2.0, help="a good run ends within this translation error")
    fg.add_argument("--tolerance-deg", type=float, default=3.0, help="... and this rotation error")
    fg.add_argument("--b0", type=float, default=1.5, help="initial exponent b_0 (the paper's 1.5)")
    fg.add_argument("--p-r", dest="p_r", type=float, default=0.5, help="the paper's p_r (next guidance level)")
    fg.set_defaults(func=cmd_evolution_fit_guided)

    de = sub.add_parser("demo", help="quick dataset + localization table (the default main job)")
    de.add_argument("-o", "--out", default="out/demo")
    de.add_argument("--azimuth", type=_finite, default=90.0)
    de.add_argument("--images-per-position", type=int, default=2)
    de.set_defaults(func=cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    for name in ("images_per_position", "jobs", "every"):
        v = getattr(args, name, None)
        if v is not None and v < 1:
            print(f"error: --{name.replace('_', '-')} must be >= 1, got {v}", file=sys.stderr)
            return EXIT_USAGE
    try:
        return int(args.func(args) or 0)
    except SupervisorError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
