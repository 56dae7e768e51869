"""The command line: ``tflearn SUBCOMMAND ...`` and ``train CONFIG [key=value ...]``.

Subcommands: ``gestures`` (write the gesture library), ``train`` (learn a basis),
``evaluate`` (re-simulate a run's basis against motions), ``simulate`` (play one motion's
torque program from a basis.json), ``render`` (animate one motion of a run, target and
reproduction side by side, as a GIF and a TensorBoard video), ``experiment`` (run one of
the thesis' chapter 4 experiments), ``report`` (write docs/results.md from their results).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _gestures(args) -> int:
    from . import gestures
    written = gestures.write(args.out, rate=args.rate, plots=not args.no_plots)
    for path in written:
        print(path)
    print(f"wrote {len(gestures.GESTURES)} gestures to {args.out}")
    return 0


def _train(args) -> int:
    from . import config
    cfg = config.load(args.config, args.overrides)
    import torch

    from . import train
    torch.set_num_threads(args.threads)
    metrics = train.run(cfg, restart=args.restart)
    overall = metrics["overall"]
    for name, m in metrics["motions"].items():
        print(f"{name:>24s}: rmse {m['rmse']:.4f} rad, tip {100 * m['tip']:.2f} cm, "
              f"torque error {100 * m['torque_rel_rms']:.2f}%{'' if m['success'] else '  (not reproduced)'}")
    print(f"M = {overall['M']}, overall rmse {overall['rmse']:.4f} rad, max tip error "
          f"{100 * overall['tip']:.2f} cm, {overall['wall_time_s']:.0f} s -> {cfg.out}")
    return 0 if overall["success"] else 1


def _evaluate(args) -> int:
    import torch

    from . import evaluate
    torch.set_num_threads(args.threads)
    metrics = evaluate.evaluate_run(args.run, data=args.data, out=args.out)
    for name, m in metrics["motions"].items():
        tag = " (synthesized)" if m.get("synthesized") else ""
        print(f"{name:>24s}: rmse {m['rmse']:.4f} rad, tip {100 * m['tip']:.2f} cm{tag}")
    print(json.dumps(metrics["overall"]))
    return 0


def _simulate(args) -> int:
    from . import evaluate
    path = evaluate.simulate_basis_motion(args.basis, args.motion, args.out, rate=args.rate,
                                          duration=args.duration)
    print(path)
    return 0


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _render(args) -> int:
    import torch

    from . import render
    torch.set_num_threads(args.threads)
    path = render.render(args.run, args.motion, out=args.out, fps=args.fps,
                         tensorboard=not args.no_tensorboard)
    print(path)
    return 0


def _experiment(args) -> int:
    import torch

    from . import experiments
    torch.set_num_threads(1)
    path = args.name if args.name.suffix == ".yaml" else Path("configs/experiments") / f"{args.name}.yaml"
    cfg = experiments.load_config(path, quick=args.quick, overrides=args.overrides)
    result = experiments.run(cfg)
    print(experiments.text_summary(result))
    print(f"{cfg.experiment}: {result['elapsed_s']:.0f} s -> {cfg.out}/results.json")
    return 0


def _report(args) -> int:
    from . import experiments
    print(experiments.report(args.runs, args.out))
    return 0


def build_parser(prog: str = "tflearn") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("gestures", help="generate the thesis' gesture library (npz + json + png)")
    p.add_argument("--out", type=Path, default=Path("runs/gestures"), help="output folder")
    p.add_argument("--rate", type=float, default=100.0, help="sampling rate in Hz (default 100)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.set_defaults(func=_gestures)

    p = sub.add_parser("train", help="learn a shared basis of torque fields (see configs/)")
    _train_args(p)

    p = sub.add_parser("evaluate", help="re-simulate a run's basis against motions")
    p.add_argument("run", type=Path, help="a run folder (with basis.json and config.yaml)")
    p.add_argument("--data", default=None, help="motions to evaluate (default: the run's data)")
    p.add_argument("--out", type=Path, default=None, help="metrics file (default RUN/evaluation.json)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.set_defaults(func=_evaluate)

    p = sub.add_parser("simulate", help="play one motion's torque program from a basis.json")
    p.add_argument("basis", type=Path)
    p.add_argument("--motion", required=True, help="motion name in the basis")
    p.add_argument("--out", type=Path, required=True, help="output .npz")
    p.add_argument("--rate", type=float, default=None, help="samples per second (default: the motion's)")
    p.add_argument("--duration", type=float, default=None, help="seconds (default: the motion's)")
    p.set_defaults(func=_simulate)

    p = sub.add_parser("render", help="animate one motion of a run: target and reproduced arm (GIF)")
    p.add_argument("run", type=Path, help="a run folder (with basis.json and config.yaml)")
    p.add_argument("--motion", required=True, help="motion name in the run's basis")
    p.add_argument("--out", type=Path, default=None, help="output .gif (default RUN/figures/MOTION.gif)")
    p.add_argument("--fps", type=_positive_int, default=25, help="frames per second (default 25)")
    p.add_argument("--no-tensorboard", action="store_true",
                   help="do not log the video to RUN/tensorboard")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.set_defaults(func=_render)

    p = sub.add_parser("experiment", help="run one of the thesis' chapter 4 experiments "
                                          "(configs/experiments/NAME.yaml)")
    p.add_argument("name", type=Path, help="basin | shared | keyframes | filtering, or a .yaml file")
    p.add_argument("overrides", nargs="*", help="dotted key=value overrides, e.g. seeds=5 jobs=1")
    p.add_argument("--quick", action="store_true", help="the config's small 'quick' size")
    p.set_defaults(func=_experiment)

    p = sub.add_parser("report", help="write docs/results.md from the experiments' results")
    p.add_argument("--runs", type=Path, default=Path("runs/experiments"),
                   help="folder of experiment outputs (default runs/experiments)")
    p.add_argument("--out", type=Path, default=Path("docs/results.md"), help="report file")
    p.set_defaults(func=_report)
    return parser


def _train_args(p) -> None:
    p.add_argument("config", type=Path, help="YAML config (e.g. configs/gestures.yaml)")
    p.add_argument("overrides", nargs="*", help="dotted key=value overrides, e.g. seed=3 out=runs/x")
    p.add_argument("--restart", action="store_true", help="discard a checkpoint in the output folder")
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads (default 1: the tensors are small, threads only add overhead)")
    p.set_defaults(func=_train)


def _run(args, command: str) -> int:
    """Run a subcommand: bad input (:class:`tflearn.errors.InputError`) is one line on
    stderr and exit status 2; any other exception is a bug and keeps its traceback."""
    from .errors import InputError
    try:
        return args.func(args)
    except InputError as err:
        print(f"{command}: error: {err}", file=sys.stderr)
        return 2


def _parse(parser: argparse.ArgumentParser, argv):
    """parse_args, except that key=value overrides may also follow options
    (``experiment basin --quick seeds=5``): argparse leaves those unrecognised."""
    args, extra = parser.parse_known_args(argv)
    if extra and hasattr(args, "overrides") and all("=" in x and not x.startswith("-") for x in extra):
        args.overrides = list(args.overrides) + extra
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    return args


def main(argv=None) -> int:
    args = _parse(build_parser(), argv)
    return _run(args, f"tflearn {args.command}")


def train_main(argv=None) -> int:
    """The ``train`` console script: ``train CONFIG [key=value ...]``."""
    p = argparse.ArgumentParser(prog="train", description="Learn a shared basis of torque fields.")
    _train_args(p)
    return _run(_parse(p, argv), "train")


if __name__ == "__main__":
    sys.exit(main())
