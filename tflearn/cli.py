"""The command line: ``tflearn COMMAND ...`` and ``train CONFIG [key=value ...]``.

One grammar: every command that uses a trained model takes a run folder or its
basis.json (MODEL); every command says what it wrote and where; bad input is one line,
``PROG: FILE: problem``, and exit status 2, before any work; anything else is a bug and
shows its traceback with a request to report it. Arguments and configs are checked
before torch is imported, so ``--help`` and refusals answer at once.
"""
from __future__ import annotations

import argparse
import contextlib
import math
import os
import signal
import sys
import threading
import traceback
from pathlib import Path

from . import __version__

DESCRIPTION = "Learn a shared basis of convergent torque fields from limb motions, and use it."
EPILOG = "MODEL is a run folder (written by train) or its basis.json."


def _commands(sub) -> str:
    """The ``commands:`` list of ``tflearn --help``: each command of the subparsers
    ``sub``, once, with its help, wrapped to 80 columns."""
    import textwrap
    helps = {a.dest: a.help for a in sub._get_subactions()}
    width = max(map(len, sub.choices)) + 2
    lines = ["commands:"]
    for name, parser in sub.choices.items():
        lines += textwrap.wrap(helps.get(name) or parser.description or "", 80,
                               initial_indent=f"  {name:<{width}}", subsequent_indent=" " * (width + 2))
    return "\n".join(lines)


def _model_paths(model: Path) -> tuple:
    """(run folder, basis.json) of a MODEL argument: a run folder or a basis.json.
    Raises :class:`InputError` naming the one that is missing."""
    from .errors import InputError
    model = Path(model)
    if model.is_dir():
        if not (model / "basis.json").exists():
            raise InputError(f"{model / 'basis.json'}: no such file (is {model} a run folder "
                             f"written by train?)")
        return model, model / "basis.json"
    if not model.exists():
        raise InputError(f"{model}: no such run folder or basis.json")
    return model.parent, model


@contextlib.contextmanager
def _out_folder(out: Path):
    """``with _out_folder(out):`` the output folder ``out`` exists inside; afterwards
    the command says so if it is new, or, when it failed, the new folder is removed again
    (:func:`tflearn.io.files.folder`)."""
    from .io.files import folder
    with folder(out) as made:
        yield
    if made:
        print(f"created {out}")


def _motion_lines(motions: dict) -> list:
    lines = []
    for name, m in motions.items():
        tags = [] if m["success"] else ["not reproduced"]
        if m.get("synthesized"):
            tags.append("synthesized")
        if m.get("failure"):
            tags.append(m["failure"])
        lines.append(f"{name:>24s}: rmse {m['rmse']:.4f} rad, tip {100 * m['tip']:.2f} cm, "
                     f"torque error {100 * m['torque_rel_rms']:.2f}%, growth {m['growth_efolds']:.2f} e-folds"
                     + (f"  ({'; '.join(tags)})" if tags else ""))
    return lines


def _gestures(args) -> int:
    from .data import gestures
    with _out_folder(args.out):
        written = gestures.write(args.out, rate=args.rate, plots=not args.no_plots)
    for path in written:
        print(path)
    print(f"wrote {len(gestures.GESTURES)} gestures ({len(written)} files) to {args.out}")
    return 0


def _train(args) -> int:
    from . import config
    overrides = list(args.overrides) + (["log.progress=false"] if args.quiet else [])
    cfg = config.load(args.config, overrides)
    import torch

    from . import parallel, train
    from .io.files import locked
    from .log import summary_table
    torch.set_num_threads(args.threads)
    with parallel.group("cpu"):           # started by torchrun: one rank of the run
        # one run at a time writes into OUT: its rank 0 holds OUT's lock
        with locked(cfg.out) if parallel.rank() == 0 else contextlib.nullcontext():
            metrics = train.run(cfg, restart=args.restart)
        if parallel.rank() == 0:
            print(summary_table(metrics, cfg.out))
    return 0 if metrics["overall"]["success"] else 1


def _evaluate(args) -> int:
    import torch

    from . import evaluate
    torch.set_num_threads(args.threads)
    run, _ = _model_paths(args.model)
    out = args.out or run / "evaluation.json"
    with _out_folder(out.parent):
        sim = {k: v for k, v in (("rtol", args.rtol), ("atol", args.atol), ("max_evals", args.max_evals))
               if v is not None}
        metrics = evaluate.evaluate_run(run, data=args.data, out=out, progress=not args.quiet, simulation=sim)
    o = metrics["overall"]
    print("\n".join(_motion_lines(metrics["motions"])))
    print(f"M = {o['M']}, overall rmse {o['rmse']:.4f} rad, max tip error {100 * o['tip']:.2f} cm, "
          f"all reproduced: {'yes' if o['success'] else 'no'}")
    synth = " and the new motions' programs, " + str(out.parent / "synthesized") if any(
        r["synthesized"] for r in metrics["motions"].values()) else ""
    print(f"wrote {out}{synth}")
    return 0


def _simulate(args) -> int:
    from . import evaluate
    _, basis = _model_paths(args.model)
    with _out_folder(args.out.parent):
        path = evaluate.simulate_basis_motion(basis, args.motion, args.out, rate=args.rate,
                                              duration=args.duration)
    print(f"wrote {path}")
    return 0


def _positive_float(text: str) -> float:
    value = float(text)
    if not 0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _render(args) -> int:
    import torch

    from . import render
    torch.set_num_threads(args.threads)
    run, _ = _model_paths(args.model)
    out = args.out if args.out is not None else run / "figures" / f"{args.motion}.gif"
    with _out_folder(out.parent):
        path = render.render(run, args.motion, out=out, fps=args.fps,
                             tensorboard=not args.no_tensorboard, progress=not args.quiet)
    print(f"wrote {path}")
    return 0


def _perturb_config(args):
    """The PerturbConfig of ``tflearn perturb`` flags, or of ``--config FILE`` (MODEL, if
    given, replacing its model). Raises :class:`InputError` (ConfigError) naming the problem."""
    from .config import CONTROLLER_NAMES, PerturbConfig, load, validate
    from .errors import InputError
    if args.config is not None:
        overrides = [f"model={args.model}"] if args.model is not None else []
        return load(args.config, overrides, PerturbConfig)
    if args.model is None or args.motion is None:
        raise InputError("perturb: give MODEL and --motion NAME (or --config FILE)")
    doc = {"model": str(args.model), "motions": [args.motion],
           "controllers": list(CONTROLLER_NAMES) if args.controller == "all" else [args.controller],
           "pushes": [{"force": _triple(args.force, "--force"), "at": args.at,
                       "duration": args.duration, "point": args.point}],
           "carry": args.carry, "out": str(args.out or Path("runs/perturb") / args.motion),
           "animation": not args.no_animation}
    return validate(doc, PerturbConfig, "perturb")


def _triple(text: str, flag: str) -> list:
    from .errors import InputError
    try:
        xs = [float(x) for x in text.split(",")]
    except ValueError:
        xs = []
    if len(xs) != 3 or not all(math.isfinite(x) for x in xs):
        raise InputError(f"{flag} must be three numbers FX,FY,FZ, got {text!r}")
    return xs


def _perturb(args) -> int:
    cfg = _perturb_config(args)
    import torch

    from .control import recovery
    torch.set_num_threads(args.threads)
    doc = recovery.run(cfg, progress=not args.quiet)
    print("\n".join(recovery.summary_lines(doc)))
    print(f"wrote {cfg.out}/results.json and {cfg.out}/figures/"
          + (f"; tensorboard in {cfg.out}/tensorboard" if cfg.tensorboard else ""))
    return 0


def _experiment(args) -> int:
    from . import experiments
    path = args.name if args.name.suffix == ".yaml" else Path("configs/experiments") / f"{args.name}.yaml"
    cfg = experiments.load_config(path, quick=args.quick, overrides=args.overrides)
    import torch
    torch.set_num_threads(1)
    result = experiments.run(cfg)
    print(experiments.text_summary(result))
    print(f"{cfg.experiment}: {result['elapsed_s']:.0f} s; wrote {cfg.out}/results.json and "
          f"{cfg.out}/figures/")
    return 0


def _report(args) -> int:
    from . import experiments
    print(f"wrote {experiments.report(args.runs, args.out)}")
    return 0


def _modes(args) -> int:
    from . import config
    from .modes.config import ModesConfig
    cfg = config.load(args.config, args.overrides, schema=ModesConfig)
    import torch

    from .modes import command as modal
    from .modes.analysis import ModalError
    torch.set_num_threads(args.threads)
    try:
        result = modal.run(cfg, out=args.out, progress=not args.quiet)
    except ModalError as err:
        raise ModalError(f"{args.config}: {err}") from None
    print(modal.table(result["modes"], cfg.table))
    fol = result["following"]
    if fol is not None:
        print(f"PD controller follows the mode motion: rms {fol['rms_rad']:.4f} rad, "
              f"max {fol['max_rad']:.4f} rad")
    print(f"wrote {len(result['written'])} files to {result['out']} (modes.json, "
          f"mode_II.npz/.png" + (", tensorboard/" if cfg.log.tensorboard else "") + ")")
    return 0


def _locomotion(args) -> int:
    from . import config
    from .modes.config import ModesConfig
    cfg = config.load(args.config, args.overrides, schema=ModesConfig)
    import torch

    from .modes import locomotion
    from .modes.analysis import ModalError
    torch.set_num_threads(args.threads)
    try:
        result = locomotion.run(cfg, out=args.out, duration=args.duration, settle=args.settle,
                                step=args.step, amplitude=args.amplitude)
    except ModalError as err:
        raise ModalError(f"{args.config}: {err}") from None
    g = result["locomotion"]
    dx, dy = g["direction_xy"]
    cost = "none (no travel)" if g["cost_of_transport"] is None else f"{g['cost_of_transport']:.3g}"
    print(f"{g['creature']}: {g['distance_m']:.4f} m in {args.duration - args.settle:g} s towards "
          f"({dx:+.3f}, {dy:+.3f}), {g['speed_body_lengths_per_s']:.4f} body lengths/s, "
          f"cost of transport {cost}")
    print(f"wrote {', '.join(p.name for p in result['written'])} to {result['out']}")
    return 0


def _bvh_import(args) -> int:
    from .mocap import clips as mocap
    amap = None
    if args.map is not None:
        from .config import read
        from .mocap.retarget import map_from_dict
        amap = map_from_dict(read(args.map), str(args.map))
    side, clips = _per_clip(args.arm, "arm", str, "right")
    fps, fps_of = _per_clip(args.fps, "fps", float, None)
    for name, x in fps_of.items():
        clips.setdefault(name, {})["fps"] = x["fps"]
    opts = mocap.ImportOptions(side=side, mirror=args.mirror, clips=clips, rate=args.rate, fps=fps,
                               gravity=args.gravity, strict=args.strict, amap=amap,
                               window=None if args.window is None else tuple(args.window),
                               busiest=args.busiest, split=args.split,
                               like=None if args.like is None else mocap.like_body(args.like))
    with _out_folder(args.out):
        report = mocap.import_clips(args.clips, args.out, opts)
    print("\n".join(mocap.report_lines(report)))
    print(f"wrote {len(report['clips'])} motions, body.yaml and report.json to {args.out}")
    return 0


def _per_clip(values, key: str, kind, default) -> tuple:
    """(the value for every clip, {clip: {key: value}}) of repeated options VALUE or
    CLIP=VALUE (``--arm moving --arm punch=left``)."""
    from .errors import InputError
    every, clips = default, {}
    for text in values or ():
        name, _, value = text.rpartition("=")
        try:
            value = kind(value)
        except ValueError:
            raise InputError(f"--{key} {text}: not a {kind.__name__} value") from None
        if name:
            clips[name] = {key: value}
        else:
            every = value
    return every, clips


def _bvh_export(args) -> int:
    import numpy as np

    from .errors import InputError
    from .mocap import clips as mocap
    from .motions import motion as motion_mod
    if args.source.suffix == ".npz":
        from .config import read_body
        from .physics.body import arm
        body = read_body(args.body) if args.body else arm()
        m = motion_mod.load(args.source, body)
        t, q = m.t.numpy(), m.q.numpy()
    else:
        if args.motion is None:
            raise InputError(f"{args.source}: --motion NAME is needed with a MODEL")
        import tempfile

        from . import evaluate
        from .io import basis as basis_io
        _, basis = _model_paths(args.source)
        body = basis_io.load(basis).body
        with tempfile.TemporaryDirectory() as tmp:
            path = evaluate.simulate_basis_motion(basis, args.motion, Path(tmp) / "sim.npz")
            data = np.load(path)
            t, q = data["t"], data["q"]
    with _out_folder(args.out.parent):
        mocap.export(body, t, q, args.out, skeleton=args.skeleton, side=args.arm, mirror=args.mirror)
    print(f"wrote {args.out}")
    return 0


def _bvh_args(sub) -> None:
    bvh = sub.add_parser("bvh", help="motion capture: import BVH clips (arm motions, body.yaml, "
                                     "report) or export a model's motion (or an .npz) as BVH").add_subparsers(
        dest="bvh_command", required=True, metavar="ACTION")
    p = bvh.add_parser("import", help="retarget BVH clips onto the arm: NAME.npz, body.yaml, report.json")
    p.add_argument("clips", nargs="+", type=Path, metavar="CLIP", help="BVH files or folders of them")
    p.add_argument("--arm", action="append", metavar="SIDE|CLIP=SIDE",
                   help="the performer's arm: right (default), left, or moving (per clip the one whose "
                        "hand travels further; left ones mirrored onto the right); CLIP=left sets one "
                        "clip's (CLIP: its file name without .bvh); repeatable")
    p.add_argument("--mirror", action="store_true", help="reflect the arms to the other side")
    p.add_argument("--out", type=Path, default=Path("runs/mocap"), help="output folder")
    p.add_argument("--rate", type=float, default=None,
                   help="output samples per second (default: each clip's own frame rate)")
    p.add_argument("--fps", action="append", metavar="FPS|CLIP=FPS",
                   help="the clips' (or one clip's) true frame rate when the header's is wrong; repeatable")
    p.add_argument("--like", type=Path, default=None, metavar="RUN",
                   help="import in the body and shoulder chart of a run, an import folder or a "
                        "body.yaml (clips for a trained run, or added to an import)")
    p.add_argument("--busiest", type=float, default=None, metavar="SECONDS",
                   help="keep each clip's busiest SECONDS (largest joint path length)")
    p.add_argument("--gravity", action="store_true", help="give the body gravity (default: none)")
    p.add_argument("--strict", action="store_true", help="stop at a bad file instead of skipping it")
    p.add_argument("--window", type=float, nargs=2, default=None, metavar=("START", "STOP"),
                   help="keep only this part of every clip (seconds; default: all of it)")
    p.add_argument("--split", type=float, default=None, metavar="SECONDS",
                   help="cut each clip (or its window) into pieces this long, each a motion NAME_partKK")
    p.add_argument("--map", type=Path, default=None,
                   help="YAML arm map for another skeleton: chest, shoulder, elbow, wrist, up, left, hinge")
    p.set_defaults(func=_bvh_import)
    p = bvh.add_parser("export", help="write a model's motion (or an .npz motion) as BVH")
    p.add_argument("source", type=Path, metavar="MODEL|MOTION.npz",
                   help="a run folder or basis.json (with --motion), or a motion .npz")
    p.add_argument("--motion", default=None, help="motion name in the model")
    p.add_argument("--body", type=Path, default=None, help="body.yaml of an .npz motion (default: the arm)")
    p.add_argument("--out", type=Path, required=True, help="output .bvh")
    p.add_argument("--skeleton", type=Path, default=None, help="a BVH clip whose arm is replaced")
    p.add_argument("--arm", choices=("right", "left"), default="right", help="the skeleton's arm")
    p.add_argument("--mirror", action="store_true", help="the motion is that arm mirrored")
    p.set_defaults(func=_bvh_export)


def build_parser(prog: str = "tflearn") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, usage="%(prog)s [-h] [--version] COMMAND ...",
                                     epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"tflearn {__version__}")
    # the commands are listed once, in the description (_commands), not again by argparse
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", help=argparse.SUPPRESS,
                                prog=prog)

    p = sub.add_parser("gestures", help="write the thesis' gesture library (NAME.npz, NAME.json, NAME.png)")
    p.add_argument("--out", type=Path, default=Path("runs/gestures"), help="output folder")
    p.add_argument("--rate", type=float, default=100.0, help="sampling rate in Hz (default 100)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.set_defaults(func=_gestures)

    p = sub.add_parser("train", help="learn a basis from motions (the same as the train command; "
                                     "see configs/)")
    _train_args(p)

    p = sub.add_parser("evaluate", help="re-simulate a trained model on motions; new motions are synthesised")
    p.add_argument("model", type=Path, metavar="MODEL", help="a run folder or its basis.json")
    p.add_argument("--data", default=None, help="motions to evaluate, or BVH clips (imported in the run's "
                                                "chart); default: the run's data")
    p.add_argument("--out", type=Path, default=None, help="metrics file (default RUN/evaluation.json)")
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.add_argument("--threads", type=_positive_int, default=1, help="torch threads (default 1)")
    p.add_argument("--rtol", type=_positive_float, default=None,
                   help="the simulations' relative tolerance (default the run's solver.path.rtol): "
                        "a reproduction that holds at a tighter one is converged")
    p.add_argument("--atol", type=_positive_float, default=None, help="and absolute (default the run's)")
    p.add_argument("--max-evals", type=_positive_int, default=None,
                   help="evaluations a simulation may take (default the run's solver.path.max_evals)")
    p.set_defaults(func=_evaluate)

    p = sub.add_parser("simulate", help="play one motion's torque program from a trained model")
    p.add_argument("model", type=Path, metavar="MODEL", help="a run folder or its basis.json")
    p.add_argument("--motion", required=True, help="motion name in the model")
    p.add_argument("--out", type=Path, required=True, help="output .npz")
    p.add_argument("--rate", type=float, default=None, help="samples per second (default: the motion's)")
    p.add_argument("--duration", type=float, default=None, help="seconds (default: the motion's)")
    p.set_defaults(func=_simulate)

    p = sub.add_parser("render", help="animate one motion: target and reproduction side by side (GIF)")
    p.add_argument("model", type=Path, metavar="MODEL", help="a run folder or its basis.json")
    p.add_argument("--motion", required=True, help="motion name in the run's model")
    p.add_argument("--out", type=Path, default=None, help="output .gif (default RUN/figures/MOTION.gif)")
    p.add_argument("--fps", type=_positive_int, default=25, help="frames per second (default 25)")
    p.add_argument("--no-tensorboard", action="store_true",
                   help="do not log the animation's frames (images) to RUN/tensorboard")
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.add_argument("--threads", type=_positive_int, default=1, help="torch threads (default 1)")
    p.set_defaults(func=_render)

    p = sub.add_parser("perturb", help="push the limb under each controller (fields, ff+pd, "
                                       "ff, pd-high) and measure its recovery")
    p.add_argument("model", type=Path, nargs="?", metavar="MODEL", help="a run folder or its basis.json")
    p.add_argument("--motion", default=None, help="motion name in the model")
    p.add_argument("--force", default="0,0,0", help="push force FX,FY,FZ in N, world axes (default 0,0,0)")
    p.add_argument("--at", type=float, default=1.0, help="push onset in s (default 1)")
    p.add_argument("--duration", type=float, default=0.1, help="push duration in s (default 0.1)")
    p.add_argument("--point", default="hand", help="hand | elbow | a link name (default hand)")
    p.add_argument("--controller", default="all", help="all | fields | ff+pd | ff | pd-high")
    p.add_argument("--carry", type=float, default=0.0, help="kg held at the hand (default 0)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default runs/perturb/MOTION)")
    p.add_argument("--no-animation", action="store_true", help="skip the GIF")
    p.add_argument("--config", type=Path, default=None,
                   help="a batch config (e.g. configs/perturb.yaml) instead of the push flags; "
                        "MODEL, if given, replaces its model")
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.add_argument("--threads", type=_positive_int, default=1, help="torch threads (default 1)")
    p.set_defaults(func=_perturb)

    from .experiments import NAMES
    p = sub.add_parser("experiment", help="run one of the thesis' chapter 4 experiments "
                                          "(configs/experiments/NAME.yaml)")
    p.add_argument("name", type=Path, help=f"{' | '.join(NAMES)}, or a .yaml file")
    p.add_argument("overrides", nargs="*", help="dotted key=value overrides, e.g. seeds=5 jobs=1")
    p.add_argument("--quick", action="store_true", help="the config's small 'quick' size")
    p.set_defaults(func=_experiment, resumes=True)

    p = sub.add_parser("report", help="write docs/results.md from the experiments' results")
    p.add_argument("--runs", type=Path, default=Path("runs/experiments"),
                   help="folder of experiment outputs (default runs/experiments)")
    p.add_argument("--out", type=Path, default=Path("docs/results.md"), help="report file")
    p.set_defaults(func=_report)

    p = sub.add_parser("modes", help="natural vibration modes of a body: frequencies, shapes, "
                                     "animations (configs/modes/)")
    p.add_argument("config", type=Path, help="YAML config (e.g. configs/modes/arm.yaml)")
    p.add_argument("overrides", nargs="*", help="dotted key=value overrides, e.g. stiffness.uniform=5")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: the config's out)")
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.add_argument("--threads", type=_positive_int, default=1, help="torch threads (default 1)")
    p.set_defaults(func=_modes)

    p = sub.add_parser("locomotion", help="a floating-base creature of a modes config driven by its "
                                          "modes on the ground: travel, speed, cost (configs/modes/)")
    p.add_argument("config", type=Path, help="YAML modes config (e.g. configs/modes/loop_creature.yaml)")
    p.add_argument("overrides", nargs="*", help="dotted key=value overrides, e.g. stiffness.uniform=2")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: the config's out)")
    p.add_argument("--duration", type=float, default=3.0, help="simulated time in s (default 3)")
    p.add_argument("--settle", type=float, default=0.5,
                   help="measure from this time in s, leaving the landing out (default 0.5)")
    p.add_argument("--step", type=float, default=5e-4, help="RK4 step in s (default 5e-4)")
    p.add_argument("--amplitude", type=float, default=None,
                   help="α of every drive in rad (default: the config's)")
    p.add_argument("--threads", type=_positive_int, default=1, help="torch threads (default 1)")
    p.set_defaults(func=_locomotion)
    _bvh_args(sub)
    parser.description = f"{DESCRIPTION}\n\n{_commands(sub)}"
    return parser


def _train_args(p) -> None:
    p.add_argument("config", type=Path, help="YAML config (e.g. configs/gestures.yaml)")
    p.add_argument("overrides", nargs="*", help="dotted key=value overrides, e.g. seed=3 out=runs/x")
    p.add_argument("--restart", action="store_true", help="discard a checkpoint in the output folder")
    p.add_argument("--quiet", action="store_true", help="no progress display (log.progress=false)")
    p.add_argument("--threads", type=_positive_int, default=1,
                   help="torch threads (default 1: the tensors are small, threads only add overhead)")
    p.set_defaults(func=_train, resumes=True)


def _run(parse, prog: str) -> int:
    """Parse the command line (``parse()``) and run its command: bad input
    (:class:`tflearn.errors.InputError`) is one line on stderr and exit status 2; Ctrl-C
    (SIGINT) anywhere is one line, ``interrupted`` (``interrupted, re-run to resume`` for
    the commands that resume) and exit status 130 (:class:`_Interrupts`); any other
    exception is a bug: its traceback, a request to report it, and exit status 3."""
    from .errors import InputError
    with _Interrupts(prog) as interrupts:
        try:
            args = interrupts.args = parse()
            return args.func(args)
        except InputError as err:
            if not interrupts.hit:
                print(f"{prog}: {err}", file=sys.stderr)
                return 2
            return interrupts.report()
        except KeyboardInterrupt:
            return interrupts.report()
        except Exception:
            if interrupts.hit:
                return interrupts.report()
            traceback.print_exc()
            print(f"{prog}: this is a bug in tflearn {__version__}; please report it with the "
                  f"command line and the traceback above", file=sys.stderr)
            return 3


class _Interrupts:
    """``with _Interrupts(prog) as i:`` the first Ctrl-C raises KeyboardInterrupt as
    usual and sets ``i.hit``: whatever exception ends the command then (a library may
    turn the KeyboardInterrupt into another one while it unwinds) is the interruption,
    reported (:meth:`report`) in one line. A second Ctrl-C, while the first unwinds, reports it
    and ends the process at once (exit status 130). The previous handler is restored on
    leaving; outside the main thread nothing is installed (signals go to the main thread)."""

    def __init__(self, prog: str):
        self.prog, self.args, self.hit, self._previous = prog, None, False, None

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handler)
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)

    def _handler(self, signum, frame):
        if self.hit:
            self.report()
            with contextlib.suppress(OSError, ValueError):     # a closed or broken stdout
                sys.stdout.flush()
            os._exit(130)
        self.hit = True
        raise KeyboardInterrupt

    def report(self) -> int:
        """Say that the command was interrupted (and that re-running it resumes, for the
        commands that do); returns the exit status, 130."""
        resumes = getattr(self.args, "resumes", False)
        print(f"{self.prog}: interrupted" + (", re-run to resume" if resumes else ""), file=sys.stderr)
        return 130


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
    return _run(lambda: _parse(build_parser(), argv), "tflearn")


def train_main(argv=None) -> int:
    """The ``train`` console script: ``train CONFIG [key=value ...]``."""
    p = argparse.ArgumentParser(prog="train", description="Learn a shared basis of torque fields "
                                "from motions (the same as tflearn train).")
    p.add_argument("--version", action="version", version=f"tflearn {__version__}")
    _train_args(p)
    return _run(lambda: _parse(p, argv), "train")


if __name__ == "__main__":
    sys.exit(main())
