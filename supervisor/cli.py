"""Command-line interface: `supervisor <command> ...`.

Errors the user can fix (bad config, bad dataset, unknown scene or driver)
print one line naming the file and the problem and exit with status 2.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from supervisor.errors import SupervisorError

EXIT_USAGE = 2


def _config(args: argparse.Namespace):
    from supervisor.config import load_config

    return load_config(args.config)


def cmd_dataset_generate(args: argparse.Namespace) -> int:
    from sim.scene import load_scene

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
    out = generate_suite(cfg, args.out, quick=args.quick, jobs=args.jobs, seed=args.seed, suite=args.suite)
    print(f"benchmark suite ready in {out} ({time.monotonic() - t0:.0f} s)")
    return 0


def cmd_model_build(args: argparse.Namespace) -> int:
    from supervisor.dataset.format import Dataset
    from supervisor.localization.offline import model_from_dataset

    cfg = _config(args)
    ds = Dataset.open(args.dataset)
    model = model_from_dataset(ds, cfg.localization)
    out = Path(args.output) if args.output else ds.root / "model.npz"
    model.save(out)
    print(f"wrote target model {out}: {len(model.points_target)} features, frame={model.frame}")
    return 0


def cmd_localize(args: argparse.Namespace) -> int:
    from supervisor.dataset.format import Dataset
    from supervisor.localization.model import TargetModel

    cfg = _config(args)
    ds = Dataset.open(args.dataset)
    model = TargetModel.load(args.model) if args.model else None
    _localize_and_report(ds, model, cfg, Path(args.out), roi=args.roi)
    return 0


def _localize_and_report(ds, model, cfg, out: Path, roi: str | None = None) -> None:
    import dataclasses

    from supervisor.localization import offline

    settings = cfg.localization if roi is None else dataclasses.replace(cfg.localization, roi=roi)
    if model is None:
        t0 = time.monotonic()
        model = offline.model_from_dataset(ds, settings)
        print(f"built target model: {len(model.points_target)} features in {time.monotonic() - t0:.1f} s",
              file=sys.stderr)
    rows = offline.localize_dataset(ds, model, settings, offline.print_progress)
    offline.write_atomic(out / "localization.csv", offline.artifacts_csv(rows))
    offline.write_atomic(out / "localization.png",
                         offline.plot_artifacts(rows, ds.kind, f"{ds.name}: n_i and error vs motion"))
    print(offline.format_table(rows, ds.kind))
    print(f"wrote {out / 'localization.csv'} and {out / 'localization.png'}")


def cmd_demo(args: argparse.Namespace) -> int:
    """Main job until the dry-run lands: a quick arc dataset, localized, n_i-vs-angle table."""
    from supervisor.dataset.format import Dataset
    from supervisor.dataset.generate import ArcSpec, generate_arc

    cfg = _config(args)
    out = Path(args.out)
    ds_dir = out / "dataset"
    print(f"generating a quick arc dataset ({cfg.scene}, azimuth {args.azimuth:g} deg, "
          f"{args.images_per_position} images per position) in {ds_dir}")
    generate_arc(cfg, ds_dir, ArcSpec(math.radians(args.azimuth), args.images_per_position), None, 0,
                 overwrite=True)
    _localize_and_report(Dataset.open(ds_dir), None, cfg, out)
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from supervisor.evaluation.experiments import run_evaluation
    from supervisor.evaluation.report import tables

    cfg = _config(args)
    report = run_evaluation(cfg, args.bench_dir, args.out, jobs=args.jobs or 2)
    print(tables(report))
    print(f"wrote {Path(args.out) / 'results.json'}, tables.md and SPL-vs-incursion plots")
    return 0


def cmd_tune(args: argparse.Namespace) -> int:
    from supervisor.evaluation.tune import format_report, tune

    cfg = _config(args)
    variants = tuple(v for v in args.variants.split(",") if v) if args.variants else None
    out = args.out or f"out/tune-{args.stage}-{args.tolerance}"
    report = tune(cfg, args.bench_dir, args.stage, args.tolerance, out, cache=args.cache, variants=variants,
                  error_aware=args.error_aware, jobs=args.jobs or 2)
    print(format_report(report))
    return 0


def cmd_dry_run(args: argparse.Namespace) -> int:
    """The product's main job: one gated arc on the sim robot with the synthetic camera and the real pipeline."""
    from supervisor.dryrun import DryRunSpec, load_motion, run_dry_run, run_replay

    cfg = _config(args)
    out = Path(args.out)
    if args.replay:
        s = run_replay(cfg, args.replay, args.stage or cfg.default_stage, out)
    else:
        motion = load_motion(args.motion) if args.motion else {"azimuth": math.radians(90.0), "scene": None,
                                                                "sweep": None}
        # explicit flags override the motion file
        azimuth = math.radians(args.azimuth) if args.azimuth is not None else motion["azimuth"]
        spec = DryRunSpec(stage=args.stage or cfg.default_stage, azimuth=azimuth, sampling=args.sampling,
                          scene=args.scene or motion["scene"], seed=args.seed, oracle=not args.no_oracle,
                          sweep=motion["sweep"])
        s = run_dry_run(cfg, spec, out)
    print(f"stage {s['stage']} ({s['sampling']}), scene {s['scene']}, azimuth {s['azimuth_deg']:g} deg: "
          f"halted at {s['halt_angle_deg']:.2f} deg ({s['halt_reason']})")
    if s.get("predicted_boundary_deg") is not None:
        print(f"  predicted boundary theta_p {s['predicted_boundary_deg']:.2f} deg, allowed "
              f"{s['theta_allowed_at_brake_deg']:.2f} deg, max overshoot {s['max_overshoot_deg']:+.3f} deg")
    if "actual_boundary_deg" in s:
        ab = s["actual_boundary_deg"]
        print(f"  actual boundary (ground truth): {ab['4mm_10deg']:.2f} deg at 4 mm/10 deg, "
              f"{ab['2mm_3deg']:.2f} deg at 2 mm/3 deg; incursion: {'YES' if s['incursion'] else 'no'}; "
              f"envelope usage {100 * s['envelope_usage']:.0f}%")
    print(f"wrote {out / 'summary.json'}, {out / 'events.jsonl'}, {out / 'timeline.png'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="supervisor", description=__doc__.splitlines()[0])
    p.add_argument("--config", default=None, help="configuration YAML (default: embedded config/default.yaml)")
    sub = p.add_subparsers(dest="command", required=True)

    ds = sub.add_parser("dataset", help="recorded datasets").add_subparsers(dest="sub", required=True)
    g = ds.add_parser("generate", help="record a dataset in simulation (paper protocol)")
    g.add_argument("out")
    g.add_argument("--scene", default=None, help="scene name or YAML path (default: the config's)")
    g.add_argument("--motion", choices=["arc", "line"], required=True)
    g.add_argument("--azimuth", type=float, default=0.0, help="arc direction [deg]: 0 up, 90 right, 270 left")
    g.add_argument("--offset", type=float, default=0.0, help="line start offset from the model view [deg]")
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
    tu.add_argument("bench_dir")
    tu.add_argument("--stage", required=True)
    tu.add_argument("--tolerance", required=True, choices=("2mm_3deg", "4mm_10deg"))
    tu.add_argument("-o", "--out", default=None, help="output directory (default out/tune-STAGE-TOLERANCE)")
    tu.add_argument("--variants", default=None,
                    help="comma-separated model variants to choose among (default: the stage's)")
    tu.add_argument("--error-aware", action="store_true", help="also tune the error-aware boundary's kappa")
    tu.add_argument("--cache", default=None, help="localization cache directory (default OUT/cache; "
                                                  "an `evaluate` OUT/cache can be reused)")
    tu.add_argument("--jobs", type=int, default=None, help="parallel processes (default 2)")
    tu.set_defaults(func=cmd_tune)

    dr = sub.add_parser("dry-run", help="gated arc on the simulated robot with the real pipeline (main job)")
    dr.add_argument("--stage", default=None, help="stage name (default: the config's default_stage)")
    dr.add_argument("--scene", default=None, help="scene name or YAML path (default: the config's)")
    dr.add_argument("--azimuth", type=float, default=None,
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
    dr.add_argument("-o", "--out", default="out/dry-run")
    dr.set_defaults(func=cmd_dry_run)

    de = sub.add_parser("demo", help="quick dataset + localization table (the default main job)")
    de.add_argument("-o", "--out", default="out/demo")
    de.add_argument("--azimuth", type=float, default=90.0)
    de.add_argument("--images-per-position", type=int, default=2)
    de.set_defaults(func=cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    for name in ("images_per_position", "jobs"):
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
