"""The ``robotdemo`` command line: parse once at the edge, call into the library, print one-line errors."""

from __future__ import annotations

import argparse
import ast
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

from robotdemo.errors import RobotDemoError

if TYPE_CHECKING:  # the CLI imports perception (and torch) only in the commands that need it
    from perception.features import FeatureConfig


def _cmd_scene(args: argparse.Namespace) -> int:
    from robotdemo.scene import Scene, SceneConfig
    from robotdemo.sim import SimConfig

    config = SceneConfig(n_objects=args.objects, seed=args.seed, sim=SimConfig(gui=args.gui))
    with Scene(config) as scene:
        scene.sim.step(int(args.seconds / config.sim.time_step_s))
        scene.sim.check_state_finite()
        rows = scene.summary()
        if args.json:
            print(json.dumps({"seed": args.seed, "objects": rows,
                              "zones": [z.__dict__ for z in scene.zones]}, indent=2))
        else:
            print(f"scene seed={args.seed}: robot RM65-B + DG-3F-lite on the table, zones "
                  + ", ".join(f"{z.name} at {z.center_xy_m}" for z in scene.zones))
            print(f"{'object':<28} {'shape':<9} {'size mm':<20} {'category':<9} {'mass kg':>8}")
            for r in rows:
                size = "x".join(f"{s:.0f}" for s in r["size_mm"])
                print(f"{r['name']:<28} {r['shape']:<9} {size:<20} {r['category']:<9} {r['mass_kg']:>8.3f}")
    return 0


def _seconds_or_none(text: str, option: str) -> float | None:
    if text.strip().lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"{option} must be a number of seconds or 'none', got {text!r}") from None


def _cmd_dataset(args: argparse.Namespace) -> int:
    from robotdemo.dataset import DatasetConfig, generate_dataset

    _output_folder(args.out, "--out")
    objects = {} if args.objects_per_instance is None else {"objects_per_instance": args.objects_per_instance}
    if args.max_slide_s is not None:
        objects["max_slide_s"] = _seconds_or_none(args.max_slide_s, "--max-slide-s")
    if args.solver_iterations is not None:
        objects["solver_iterations"] = args.solver_iterations
    config = DatasetConfig(strokes_per_instance=args.strokes_per_instance, **objects, seed=args.seed, env=args.env,
                           categories=tuple(args.categories.split(",")) if args.categories else None)
    manifest = generate_dataset(args.out, config, workers=args.workers, progress=not args.quiet)
    n = sum(s["n_strokes"] for s in manifest["shards"])
    failed = sum(s["failed_strokes"] for s in manifest["shards"])
    print(f"{args.out}: {n} strokes in {len(manifest['shards'])} shards ({failed} could not be recorded)")
    return 0


def _cmd_plot_strokes(args: argparse.Namespace) -> int:
    from perception.dataset import load_dataset
    from robotdemo.plots import plot_strokes

    records = load_dataset(args.data).records
    chosen, seen = [], set()
    for rec in records:  # the first stroke of each category, in catalogue order of appearance
        if rec.category not in seen:
            seen.add(rec.category)
            chosen.append(rec)
    print(plot_strokes(chosen[: args.max], args.out))
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from perception.sensor_use import sensor_use_from_dict, shut_out_warning
    from perception.train import TrainConfig, train_command

    defaults = TrainConfig()
    overrides = tuple((k, v) for k, v in (("dropout", args.dropout),) if v is not None) + tuple(
        _model_option(text) for text in args.model_option)
    config = TrainConfig(model=args.model, task=args.task, epochs=args.epochs, batch_size=args.batch_size,
                         seed=args.seed, device=args.device,
                         lr=defaults.lr if args.lr is None else args.lr,
                         weight_decay=defaults.weight_decay if args.weight_decay is None else args.weight_decay,
                         feature_noise_std=(defaults.feature_noise_std if args.feature_noise is None
                                            else args.feature_noise),
                         split_by_object=args.split_by_object, val_by_instance=args.val_by_instance,
                         val_fraction=defaults.val_fraction if args.val_fraction is None else args.val_fraction,
                         group_by_length=args.group_by_length,
                         modality_dropout=args.modality_dropout, train_fraction=args.train_fraction,
                         warmup_epochs=args.warmup_epochs, label_smoothing=args.label_smoothing,
                         time_crop=args.time_crop, ema_decay=args.ema_decay, feature_mask=args.feature_mask,
                         mixup_alpha=args.mixup, aux_parameters_weight=args.aux_parameters, sam_rho=args.sam_rho,
                         batch_per_class=args.batch_per_class,
                         corruption_ratio=args.corruption_ratio,
                         corruption_std=args.corruption_std,
                         model_overrides=overrides,
                         feature_config=_feature_config(args.modalities, args.accel_axes))
    _output_folder(args.out, "--out")
    metrics = train_command(args.data, args.out, config, fold=args.fold, command=" ".join(sys.argv),
                            progress=not args.quiet,
                            aux_targets_of=_drawn_log_parameters if config.aux_parameters_weight > 0 else None)
    print(json.dumps(metrics, indent=2, default=str))
    warning = shut_out_warning(sensor_use_from_dict(metrics["val_sensor_use"]))
    if warning:
        print(warning, file=sys.stderr)
    return 0


def _drawn_log_parameters(records):
    """Each stroke's object's log material parameters, drawn again from its meta (``--aux-parameters``)."""
    from perception.parameter_probe import log_parameters
    from robotdemo.dataset import drawn_materials

    return log_parameters(drawn_materials(records))


ACCEL_AXES_CHOICES = ("sum", "normal-tangential")
"""``--accel-axes`` values: the keys of :data:`perception.features.ACCEL_AXES` (named here so that building the
parser does not import the front end and torch)."""


def _feature_config(modalities: str | None, accel_axes: str = "sum") -> FeatureConfig:
    """The default front end, restricted to ``--modalities`` when given, its accelerometer spectra grouped by
    ``--accel-axes``."""
    from perception.features import FeatureConfig, with_accel_axes

    config = FeatureConfig()
    if modalities is not None:
        config = FeatureConfig(modalities=tuple(m.strip() for m in modalities.split(",") if m.strip()))
    return with_accel_axes(config, accel_axes)


def _model_option(text: str) -> tuple[str, object]:
    """``"d_model=32"`` -> ("d_model", 32): a Python literal after the first '=' (a string in quotes:
    ``"gate_pool='hidden'"``)."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise ValueError(f"--model-option expects KEY=VALUE (for example d_model=32), got {text!r}")
    try:
        parsed = ast.literal_eval(value.strip())
    except (ValueError, SyntaxError):
        raise ValueError(f"--model-option {text!r}: {value!r} is not a number, bool, tuple or quoted string") from None
    return key.strip(), parsed


def _cmd_convert_lmt(args: argparse.Namespace) -> int:
    from perception.lmt import LMTConfig, convert_lmt

    _output_folder(args.out, "--out")
    config = LMTConfig(sound_rate_hz=args.sound_rate_hz, force_rate_hz=args.force_rate_hz,
                       accel_rate_hz=args.accel_rate_hz, resample=not args.no_resample, skip_bad=args.skip_bad,
                       max_duration_mismatch=args.max_duration_mismatch,
                       combustible_categories=frozenset(c.strip() for c in (args.combustible or "").split(",")
                                                        if c.strip()))
    result = convert_lmt(args.src, args.out, config, progress=not args.quiet)
    absent = ", ".join(f"{m} {n}" for m, n in result.absent_streams.items() if n) or "none"
    print(f"{args.out}: {result.n_recordings} recordings; {len(result.skipped_outside)} .mat files outside a material "
          f"folder not read; {len(result.skipped_bad)} skipped as malformed; recordings without a stream: {absent}")
    for path, problem in result.skipped_bad[:10]:
        print(f"  skipped {path}: {problem}")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from perception.evaluate import command_config, evaluate_command, evaluation_status

    if args.status:
        config = command_config(args.quick, not args.no_ablation, not args.no_robustness, args.corruption_stds,
                                args.seeds, single_sensor=not args.no_single_sensor, accel_axes=args.accel_axes)
        status = evaluation_status(args.data, args.out, fire_dir=args.fire, config=config)
        print(json.dumps(status, indent=2))
        for name, match in status["data"].items():
            if not match["kept"] and "closest" in match:
                print(f"note: the {name} data set is not the one the stored runs were trained on: "
                      f"{match['differing_shards']} of {match['shards']} shards differ from {match['closest']} "
                      f"({'same' if match['same_code_and_options'] else 'other'} recorder code and options; numerics "
                      f"changed: {'; '.join(match['numerics_changed']) or 'none'}); see perception/numerics.py",
                      file=sys.stderr)
        return 0
    _output_folder(args.out, "--out")
    summary = evaluate_command(args.data, args.out, quick=args.quick, fire_dir=args.fire, device=args.device,
                               seeds=args.seeds, command=" ".join(sys.argv), progress=not args.quiet,
                               workers=args.workers, ablation=not args.no_ablation,
                               robustness=not args.no_robustness, corruption_stds=args.corruption_stds,
                               single_sensor=not args.no_single_sensor, accel_axes=args.accel_axes)
    print(json.dumps(summary, indent=2, default=str))
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from robotdemo.demo import DEFAULT_CHECKPOINT, DemoConfig, run_demo
    from robotdemo.viewer import viewer_config_from_args

    _output_file(args.report, "--report")
    _output_file(args.record_html, "--record")
    viewer = viewer_config_from_args(args)
    if (args.realtime or args.hold) and not (viewer is not None and viewer.live):
        raise RobotDemoError("--realtime and --hold are for watching the live view: add --meshcat")
    config = DemoConfig(n_objects=args.objects, seed=args.seed, environment=args.env,
                        checkpoint=Path(args.checkpoint) if args.checkpoint else DEFAULT_CHECKPOINT,
                        report_path=Path(args.report) if args.report else None, viewer=viewer,
                        record_path=args.record_html, realtime=args.realtime, hold=args.hold)
    run_demo(config)
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from perception.seed_pairs import compare_arms, format_comparison, parse_pair, plot_comparison

    _output_file(args.json_out, "--json")
    _output_file(args.png, "--png")
    result = compare_arms(args.runs, [parse_pair(p) for p in args.pair])
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(result, indent=2), encoding="utf-8")
    if args.png:
        plot_comparison(args.png, result)
    print(format_comparison(result))
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "ik":
        from robotdemo.benchmarks.ik_bench import run_ik_benchmark
        result = run_ik_benchmark(n_poses=args.n or 1000, seed=args.seed)
    elif args.what == "trajectory":
        from robotdemo.benchmarks.trajectory_bench import run_trajectory_benchmark
        result = run_trajectory_benchmark(n_plans=args.n or 1000, seed=args.seed)
    elif args.what == "inference":
        from perception.bench_inference import run_inference_benchmark
        result = run_inference_benchmark(args.checkpoint or "touchformer", n=args.n or 200, duration_s=args.stroke_s,
                                         seed=args.seed)
    elif args.what == "demo":
        from robotdemo.demo import DEFAULT_CHECKPOINT, run_demo_bench
        result = run_demo_bench(seeds=args.seeds, n_objects=args.objects, environment="fire",
                                checkpoint=Path(args.checkpoint) if args.checkpoint else DEFAULT_CHECKPOINT,
                                first_seed=args.seed, oracle=args.oracle)
    elif args.what == "reference":
        if not args.data:
            raise RobotDemoError("bench reference needs --data DIR (a data set folder)")
        from perception.dataset import load_dataset
        from perception.reference_classifier import honesty_check
        result = {"data": args.data, **honesty_check(load_dataset(args.data).records, seed=args.seed)}
    elif args.what == "statistics":
        if not args.data:
            raise RobotDemoError("bench statistics needs --data DIR (a data set folder)")
        from perception.dataset import load_dataset
        from perception.pooled_statistics import PooledStatisticsConfig, run_pooled_statistics
        config = PooledStatisticsConfig(read_test=args.read_test, features=_feature_config(None, args.accel_axes))
        result = {"data": args.data, **run_pooled_statistics(load_dataset(args.data).records, config, progress=True)}
    elif args.what == "parameters":
        if not args.data:
            raise RobotDemoError("bench parameters needs --data DIR (a data set recorded by robotdemo dataset)")
        _output_file(args.plot, "--plot")
        from robotdemo.benchmarks.parameters_bench import run_parameters_benchmark
        result = run_parameters_benchmark(args.data, read_test=args.read_test,
                                          features=_feature_config(None, args.accel_axes))
        if args.plot:
            from perception.parameter_probe import plot_parameter_probe
            result["plot"] = str(plot_parameter_probe(args.plot, result))
    elif args.what == "timing":
        from perception.timing_control import TimingControlConfig, run_timing_control
        result = run_timing_control(TimingControlConfig(n_train=args.n or 1000), progress=True)
    elif args.what == "classifier":
        if not args.data:
            raise RobotDemoError("bench classifier needs --data DIR (the data set the checkpoint was trained on)")
        from robotdemo.benchmarks.classifier_bench import run_classifier_benchmark
        from robotdemo.demo import DEFAULT_CHECKPOINT
        result = run_classifier_benchmark(args.checkpoint or DEFAULT_CHECKPOINT, args.data)
    elif args.what == "stroke":
        from robotdemo.benchmarks.stroke_bench import run_stroke_benchmark
        result = run_stroke_benchmark(clamped=args.clamped, solver_iterations=_counts(args.solver_iterations))
    elif args.what == "emulation":
        from robotdemo.benchmarks.emulation_bench import run_emulation_benchmark
        result = run_emulation_benchmark(n_strokes=args.n or 6, seed=args.seed)
    else:  # pragma: no cover - argparse restricts choices
        raise RobotDemoError(f"unknown benchmark {args.what!r}")
    print(json.dumps(result, indent=2) if args.json else _format_flat(result))
    return 0


def _counts(text: str) -> tuple[int, ...]:
    try:
        counts = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise ValueError(f"--solver-iterations must be whole numbers separated by commas, got {text!r}") from None
    if not counts or min(counts) < 1:
        raise ValueError(f"--solver-iterations must be >= 1, got {text!r}")
    return counts


def _format_flat(result: dict, prefix: str = "") -> str:
    lines = []
    for key, value in result.items():
        if isinstance(value, dict):
            lines.append(_format_flat(value, f"{prefix}{key}."))
        else:
            lines.append(f"{prefix}{key}: {value}")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    from robotdemo.viewer import add_viewer_arguments

    parser = argparse.ArgumentParser(prog="robotdemo", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    scene = sub.add_parser("scene", help="build the sorting scene headless and print what it holds")
    scene.add_argument("--objects", type=_non_negative_int, default=6)
    scene.add_argument("--seed", type=_non_negative_int, default=0)
    scene.add_argument("--seconds", type=_seconds, default=1.0, help="simulated seconds to step after building")
    scene.add_argument("--gui", action="store_true", help="open PyBullet's GUI instead of running headless")
    scene.add_argument("--json", action="store_true")
    scene.set_defaults(func=_cmd_scene)

    demo = sub.add_parser("demo", help="sort the objects by touch (headless unless --meshcat or --record)")
    demo.add_argument("--objects", type=_non_negative_int, default=6)
    demo.add_argument("--seed", type=_non_negative_int, default=0)
    demo.add_argument("--env", choices=["clean", "fire"], default="fire", help="sensor environment")
    demo.add_argument("--checkpoint", default=None, help="classifier checkpoint folder "
                      "(default robotdemo/checkpoints/touchformer_fire)")
    demo.add_argument("--report", default=None, metavar="FILE.json", help="write the JSON report here")
    add_viewer_arguments(demo)
    demo.add_argument("--realtime", action="store_true",
                      help="with --meshcat: run no faster than the wall clock, for watching")
    demo.add_argument("--hold", action="store_true",
                      help="with --meshcat: keep serving the view after the run until Ctrl-C")
    demo.set_defaults(func=_cmd_demo)

    dataset = sub.add_parser("dataset", help="record the stroke data set (real strokes in PyBullet + sensor emulation)")
    dataset.add_argument("--out", required=True, help="output folder (resumed if it exists)")
    dataset.add_argument("--strokes-per-instance", type=_positive_int, default=30)
    dataset.add_argument("--objects-per-instance", type=int, default=None,
                         help="distinct objects per material instance (default: DatasetConfig's, 10)")
    dataset.add_argument("--seed", type=_non_negative_int, default=0)
    dataset.add_argument("--workers", type=_positive_int, default=1)
    dataset.add_argument("--env", choices=["clean", "fire"], default="clean")
    dataset.add_argument("--categories", default=None, help="comma-separated subset, e.g. metal,wood")
    dataset.add_argument("--max-slide-s", default=None, metavar="S",
                         help="cut each drawn slide to what its speed covers in S seconds, not below 20 mm "
                              "(default 0.8; 'none': the drawn length stands)")
    dataset.add_argument("--solver-iterations", type=int, default=None, metavar="N",
                         help="physics solver iterations per step while recording (default 75, DatasetConfig's)")
    dataset.add_argument("--quiet", action="store_true", help="no progress bar")
    dataset.set_defaults(func=_cmd_dataset)

    plot = sub.add_parser("plot-strokes", help="the four streams side by side for a few materials (PNG)")
    plot.add_argument("data", help="a data set folder")
    plot.add_argument("--out", required=True, help="PNG file to write")
    plot.add_argument("--max", type=int, default=7, help="how many strokes (one per category)")
    plot.set_defaults(func=_cmd_plot_strokes)

    train = sub.add_parser("train", help="train a model on a data set (safetensors checkpoint, resumable)")
    train.add_argument("--data", required=True)
    train.add_argument("--task", choices=["ssmc", "usmc", "fine"], default="ssmc")
    train.add_argument("--model", default="touchformer",
                       choices=["touchformer", "touchformer_mag", "touchformer_fusion", "touchformer_soft", "lstm",
                                "mtcnn"])
    train.add_argument("--out", required=True)
    train.add_argument("--epochs", type=int, default=50)
    train.add_argument("--batch-size", type=int, default=32)
    train.add_argument("--seed", type=_non_negative_int, default=0)
    train.add_argument("--fold", type=int, default=0, help="usmc: which of the 5 folds to hold out")
    train.add_argument("--lr", type=float, default=None, help="learning rate (default 3e-3)")
    train.add_argument("--weight-decay", type=float, default=None, help="AdamW weight decay (default 0.01)")
    train.add_argument("--feature-noise", type=float, default=None,
                       help="augmentation noise on normalised features, training std units (default 0.05)")
    train.add_argument("--dropout", type=float, default=None, help="the model's dropout (default: the model's)")
    train.add_argument("--split-by-object", action="store_true",
                       help="ssmc/fine: test and validation strokes come from objects not trained on")
    train.add_argument("--val-by-instance", action="store_true",
                       help="ssmc/usmc: validation strokes come from material instances not trained on")
    train.add_argument("--val-fraction", type=float, default=None,
                       help="validation share of the training part (default 0.15)")
    train.add_argument("--group-by-length", action="store_true",
                       help="batches of strokes of similar length (less padding, faster epochs)")
    train.add_argument("--modality-dropout", type=float, default=0.0,
                       help="training: probability of removing each modality of a stroke (default 0)")
    train.add_argument("--train-fraction", type=float, default=1.0,
                       help="train on this share of the training part, stratified (learning curves; default 1)")
    train.add_argument("--warmup-epochs", type=int, default=0,
                       help="linear lr warmup over this many epochs before the cosine decay (default 0)")
    train.add_argument("--label-smoothing", type=float, default=0.0,
                       help="cross-entropy label smoothing (default 0, the paper's loss)")
    train.add_argument("--time-crop", type=float, default=1.0, metavar="SHARE",
                       help="training: cut each stroke to a random window of at least this share of it "
                            "(default 1: off)")
    train.add_argument("--aux-parameters", type=float, default=0.0, metavar="WEIGHT",
                       help="training, not the paper's: also regress each training stroke's material parameters "
                            "(drawn again from its meta; privileged information of the simulator) from the "
                            "embedding, at this loss weight (default 0: off)")
    train.add_argument("--ema-decay", type=float, default=0.0, metavar="DECAY",
                       help="validate and keep an exponential moving average of the weights with this decay per "
                            "step (default 0: off, the plain weights)")
    train.add_argument("--feature-mask", type=float, default=0.0, metavar="SHARE",
                       help="training: SpecAugment-style masking, one band of channels and one span of steps of each "
                            "stream zeroed, each up to this share wide (default 0: off)")
    train.add_argument("--mixup", type=float, default=0.0, metavar="ALPHA",
                       help="training: mixup, each batch blended with a shuffled copy of itself at a Beta(ALPHA, "
                            "ALPHA) weight, labels blended alike (default 0: off)")
    train.add_argument("--sam-rho", type=float, default=0.0, metavar="RHO",
                       help="training, not the paper's: sharpness-aware minimisation, each step's gradient taken at "
                            "the weights moved RHO up the batch's gradient (default 0: off, plain AdamW)")
    train.add_argument("--batch-per-class", type=_non_negative_int, default=0, metavar="K",
                       help="training, not the paper's: batches of BATCH_SIZE / K labels with K strokes each, so that "
                            "every stroke has positives for CER's contrastive loss (default 0: off)")
    train.add_argument("--corruption-ratio", type=float, default=0.0, metavar="P",
                       help="robustness experiment: each modality of each stroke gets N(0, STD^2) noise (training "
                            "std units) with probability P, in training, validation and test (default 0)")
    train.add_argument("--corruption-std", type=float, default=1.0, metavar="STD",
                       help="the robustness experiment's noise std, units of the per-channel training std "
                            "(default 1, as evaluate's)")
    train.add_argument("--modalities", default=None, metavar="S,N,...",
                       help="train on these sensors only, comma-separated among sound, normal, friction, accel; "
                            "the checkpoint then ignores the others (default: all four)")
    train.add_argument("--accel-axes", choices=ACCEL_AXES_CHOICES, default="sum",
                       help="not the paper's: 'normal-tangential' gives the accelerometer's pad-normal (z) and in-plane "
                            "(x + y) vibration spectra side by side instead of one spectrum of the power summed "
                            "over the three axes (default sum); needs a 3-axis accelerometer")
    train.add_argument("--model-option", action="append", default=[], metavar="KEY=VALUE",
                       help="a field of the model's config, e.g. d_model=32 (repeatable)")
    train.add_argument("--device", default="auto", help="auto (GPU when present), cpu or cuda")
    train.add_argument("--quiet", action="store_true")
    train.set_defaults(func=_cmd_train)

    lmt = sub.add_parser("convert-lmt", help="convert recordings in the TUM/LMT haptic database layout into a "
                                             "data set folder (to train on real data)")
    lmt.add_argument("src", help="folder holding C<c>_S<s>_M<m>/ (or C<c>/S<s>/M<m>/) folders of .mat recordings")
    lmt.add_argument("--out", required=True, help="data set folder to write")
    lmt.add_argument("--sound-rate-hz", type=float, default=44_100.0, help="sound rate (default 44100)")
    lmt.add_argument("--force-rate-hz", type=float, default=10_000.0,
                     help="normalForce and frictionForce rate (default 10000, Texplorer2's; some loaders use 3000)")
    lmt.add_argument("--accel-rate-hz", type=float, default=10_000.0, help="accelDFT rate (default 10000)")
    lmt.add_argument("--max-duration-mismatch", type=float, default=0.10, metavar="FRACTION",
                     help="refuse a recording whose streams last more than this share apart at the given rates "
                          "(a guard against a wrong rate; default 0.1)")
    lmt.add_argument("--no-resample", action="store_true",
                     help="keep the source rates instead of resampling forces and acceleration to the pad's")
    lmt.add_argument("--skip-bad", action="store_true",
                     help="skip malformed recordings (counted and listed) instead of stopping at the first")
    lmt.add_argument("--combustible", default=None, metavar="C1,C3",
                     help="categories to label combustible (LMT has no such label; default none)")
    lmt.add_argument("--quiet", action="store_true")
    lmt.set_defaults(func=_cmd_convert_lmt)

    evaluate = sub.add_parser("evaluate", help="the paper's experiments on our data: REPORT.md, JSON, plots")
    evaluate.add_argument("--data", required=True)
    evaluate.add_argument("--out", default="reports")
    evaluate.add_argument("--fire", default=None, help="a fire-environment data set: the clean -> fire shift, and "
                          "the robustness runs scored zero-shot on its strokes")
    evaluate.add_argument("--quick", action="store_true", help="a small run (few epochs, one seed)")
    evaluate.add_argument("--seeds", type=_non_negative_int, nargs="+", default=None)
    evaluate.add_argument("--device", default="auto")
    evaluate.add_argument("--workers", type=_positive_int, default=1,
                          help="train the runs in this many processes first (one torch thread each)")
    evaluate.add_argument("--no-ablation", action="store_true", help="leave the ablation runs out")
    evaluate.add_argument("--no-robustness", action="store_true", help="leave the robustness curve out")
    evaluate.add_argument("--no-single-sensor", action="store_true",
                          help="leave out the networks trained on one sensor at a time")
    evaluate.add_argument("--corruption-stds", type=float, nargs="+", default=None, metavar="STD",
                          help="the robustness curve's noise intensities, stds in units of the per-channel "
                               "training feature std (default 1 3 5)")
    evaluate.add_argument("--accel-axes", choices=ACCEL_AXES_CHOICES, default="sum",
                          help="not the paper's: every network's accelerometer front end as train's --accel-axes "
                               "(default sum); the report lists it among the deviations. Give it its own --out: "
                               "its runs take the same folder names")
    evaluate.add_argument("--status", action="store_true",
                          help="print how many of the evaluation's network runs the run store in --out holds, per "
                               "experiment, and the test accuracies of those stored so far (interim), and stop "
                               "(nothing is trained or written)")
    evaluate.add_argument("--quiet", action="store_true")
    evaluate.set_defaults(func=_cmd_evaluate)

    compare = sub.add_parser("compare", help="pair training runs of two recipes by seed and fold: mean difference, "
                             "95 %% t-interval, paired t-test, runs won and lost")
    compare.add_argument("runs", help="a folder with one folder per arm, each holding robotdemo train runs "
                         "(ARM/.../metrics.json)")
    compare.add_argument("--pair", action="append", default=[], metavar="ARM:AGAINST",
                         help="compare ARM against AGAINST (repeatable); without it only each arm's mean is shown")
    compare.add_argument("--json", dest="json_out", default=None, metavar="FILE.json", help="write the figures here")
    compare.add_argument("--png", default=None, metavar="FILE.png", help="plot each pair's per-run differences")
    compare.set_defaults(func=_cmd_compare)

    bench = sub.add_parser("bench", help="benchmarks that print medians and ratios against a peer")
    bench.add_argument("what", choices=["ik", "trajectory", "stroke", "emulation", "inference", "demo", "reference",
                                         "statistics", "parameters", "classifier", "timing"])
    bench.add_argument("--checkpoint", default=None, help="inference: a checkpoint folder (default: a fresh model); "
                       "demo, classifier: the classifier (default robotdemo/checkpoints/touchformer_fire)")
    bench.add_argument("--data", default=None, help="reference: the data set to run the honesty check on (also each "
                       "stream's own accuracy); statistics, parameters: the data set whose training splits to fit on; "
                       "classifier: the data set the checkpoint was trained on (its held-out part is used)")
    bench.add_argument("--read-test", action="store_true",
                       help="statistics, parameters: also score the test parts (by default the validation parts "
                            "only, which the networks' epochs were chosen on)")
    bench.add_argument("--seeds", type=_positive_int, default=10, help="demo: number of seeds (fire environment)")
    bench.add_argument("--objects", type=_positive_int, default=6, help="demo: objects per seed")
    bench.add_argument("--oracle", action="store_true",
                       help="demo: classify with the true labels (the robot's handling alone; a diagnostic)")
    bench.add_argument("--n", type=_positive_int, default=None,
                       help="ik, trajectory: poses / plans (default 1000); inference: strokes (default 200); "
                            "emulation: strokes (default 6); timing: training strokes per seed (default 1000)")
    bench.add_argument("--seed", type=_non_negative_int, default=0)
    bench.add_argument("--stroke-s", type=float, default=1.0,
                       help="inference: length of the synthetic stroke, s (the data sets' median is about 2.2)")
    bench.add_argument("--clamped", action="store_true",
                       help="stroke: on the data set's fixture (the object clamped and free of the table)")
    bench.add_argument("--solver-iterations", default="100", metavar="N[,N...]",
                       help="stroke: the physics solver's iterations per step, one run per count (default 100)")
    bench.add_argument("--plot", default=None, metavar="FILE.png",
                       help="parameters: also draw the recovery and the oracle as a PNG")
    bench.add_argument("--accel-axes", choices=ACCEL_AXES_CHOICES, default="sum",
                       help="statistics, parameters: the accelerometer front end whose frames are pooled, as train's "
                            "--accel-axes (default sum)")
    bench.add_argument("--json", action="store_true")
    bench.set_defaults(func=_cmd_bench)
    return parser


_USER_ERROR_NAMES = {"TrainError", "CheckpointError"}
"""perception's errors about bad input that are not ValueErrors, and their subclasses (checked by name:
importing perception.train here would load torch for every command)."""


def _is_user_error(exc: BaseException) -> bool:
    """Bad input or a path that cannot be read or written (OSError: missing, a file where a folder belongs,
    no permission): one line. Anything else is a bug and keeps its traceback."""
    return (isinstance(exc, (RobotDemoError, ValueError, OSError))
            or any(cls.__name__ in _USER_ERROR_NAMES for cls in type(exc).__mro__))


def _int_at_least(minimum: int) -> Callable[[str], int]:
    """An argparse type: a whole number >= ``minimum`` (argparse names the option in its error)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {minimum}, got {text!r}")
        return value
    return parse


_positive_int, _non_negative_int = _int_at_least(1), _int_at_least(0)


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds >= 0, got {text!r}")
    return value


def _output_folder(path: str, option: str) -> None:
    """Fail before any work if ``path`` exists and is not a folder."""
    if Path(path).exists() and not Path(path).is_dir():
        raise RobotDemoError(f"{option} {path}: exists and is not a folder")


def _output_file(path: str | None, option: str) -> None:
    """Fail before any work if ``path`` is a folder or its parent is not one."""
    if path is None:
        return
    target = Path(path)
    if target.is_dir():
        raise RobotDemoError(f"{option} {path}: is a folder; give a file name")
    parent = target.parent
    if parent.exists() and not parent.is_dir():
        raise RobotDemoError(f"{option} {path}: {parent} is not a folder")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except Exception as exc:  # noqa: BLE001 - user errors become one line; anything else is a bug: re-raise
        if not _is_user_error(exc):
            raise
        print(f"robotdemo: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("robotdemo: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
