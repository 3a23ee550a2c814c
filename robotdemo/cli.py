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


def _cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "ik":
        from robotdemo.benchmarks.ik_bench import run_ik_benchmark
        result = run_ik_benchmark(n_poses=args.n or 1000, seed=args.seed)
    elif args.what == "trajectory":
        from robotdemo.benchmarks.trajectory_bench import run_trajectory_benchmark
        result = run_trajectory_benchmark(n_plans=args.n or 1000, seed=args.seed)
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

    bench = sub.add_parser("bench", help="benchmarks that print medians and ratios against a peer")
    bench.add_argument("what", choices=["ik", "trajectory"])
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
