"""The ``robotdemo`` command line: parse once at the edge, call into the library, print one-line errors."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Callable, Sequence

from robotdemo.errors import RobotDemoError


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


def _cmd_dataset(args: argparse.Namespace) -> int:
    from robotdemo.dataset import DatasetConfig, generate_dataset

    config = DatasetConfig(strokes_per_instance=args.strokes_per_instance, objects_per_instance=args.objects_per_instance,
                           seed=args.seed, env=args.env,
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


def _cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "ik":
        from robotdemo.benchmarks.ik_bench import run_ik_benchmark
        result = run_ik_benchmark(n_poses=args.n or 1000, seed=args.seed)
    elif args.what == "trajectory":
        from robotdemo.benchmarks.trajectory_bench import run_trajectory_benchmark
        result = run_trajectory_benchmark(n_plans=args.n or 1000, seed=args.seed)
    elif args.what == "emulation":
        from robotdemo.benchmarks.emulation_bench import run_emulation_benchmark
        result = run_emulation_benchmark(n_strokes=args.n or 6, seed=args.seed)
    else:  # pragma: no cover - argparse restricts choices
        raise RobotDemoError(f"unknown benchmark {args.what!r}")
    print(json.dumps(result, indent=2) if args.json else _format_flat(result))
    return 0


def _format_flat(result: dict, prefix: str = "") -> str:
    lines = []
    for key, value in result.items():
        if isinstance(value, dict):
            lines.append(_format_flat(value, f"{prefix}{key}."))
        else:
            lines.append(f"{prefix}{key}: {value}")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="robotdemo", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    scene = sub.add_parser("scene", help="build the sorting scene headless and print what it holds")
    scene.add_argument("--objects", type=int, default=6)
    scene.add_argument("--seed", type=int, default=0)
    scene.add_argument("--seconds", type=float, default=1.0, help="simulated seconds to step after building")
    scene.add_argument("--gui", action="store_true", help="open PyBullet's GUI instead of running headless")
    scene.add_argument("--json", action="store_true")
    scene.set_defaults(func=_cmd_scene)

    demo = sub.add_parser("demo", help="the headless demo (for now: builds the scene and prints it)")
    demo.add_argument("--objects", type=int, default=6)
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--seconds", type=float, default=1.0)
    demo.add_argument("--gui", action="store_true")
    demo.add_argument("--json", action="store_true")
    demo.set_defaults(func=_cmd_scene)

    dataset = sub.add_parser("dataset", help="record the stroke data set (real strokes in PyBullet + sensor emulation)")
    dataset.add_argument("--out", required=True, help="output folder (resumed if it exists)")
    dataset.add_argument("--strokes-per-instance", type=int, default=30)
    dataset.add_argument("--objects-per-instance", type=int, default=3)
    dataset.add_argument("--seed", type=int, default=0)
    dataset.add_argument("--workers", type=int, default=1)
    dataset.add_argument("--env", choices=["clean", "fire"], default="clean")
    dataset.add_argument("--categories", default=None, help="comma-separated subset, e.g. metal,wood")
    dataset.add_argument("--quiet", action="store_true", help="no progress bar")
    dataset.set_defaults(func=_cmd_dataset)

    plot = sub.add_parser("plot-strokes", help="the four streams side by side for a few materials (PNG)")
    plot.add_argument("data", help="a data set folder")
    plot.add_argument("--out", required=True, help="PNG file to write")
    plot.add_argument("--max", type=int, default=7, help="how many strokes (one per category)")
    plot.set_defaults(func=_cmd_plot_strokes)

    bench = sub.add_parser("bench", help="benchmarks that print medians and ratios against a peer")
    bench.add_argument("what", choices=["ik", "trajectory", "emulation"])
    bench.add_argument("--n", type=int, default=None, help="number of poses / plans (default 1000)")
    bench.add_argument("--seed", type=int, default=0)
    bench.add_argument("--json", action="store_true")
    bench.set_defaults(func=_cmd_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except (RobotDemoError, ValueError, FileNotFoundError) as exc:
        print(f"robotdemo: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("robotdemo: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
