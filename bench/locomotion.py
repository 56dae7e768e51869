"""Locomotion of the paper's two simple creatures (Kry et al. 2007, §4.1, figure 2,
table 1; docs/modes.md, "Locomotion"): the floating-base creature of
configs/modes/NAME.yaml on a free joint, on the ground, its joints driven by a PD
controller (gain: the analysis stiffness) whose set point follows the config's
``motion.drives`` (the two lowest elastic modes, 90° apart), gravity on.

    PYTHONPATH=. python bench/locomotion.py linear_creature loop_creature [--out DIR]
        [--duration S] [--step H] [--amplitude A]     (~3 min per creature on one core)

Prints and writes OUT/NAME/locomotion.json (speed in body lengths per second, direction,
cost of transport, right-hand-side evaluations, the options used) and NAME.gif.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, replace
from pathlib import Path

import torch

from tflearn import config
from tflearn.modes import analysis as md
from tflearn.modes import command as modal
from tflearn.modes import locomotion as lo
from tflearn.modes import motion as mm
from tflearn.modes.config import ModesConfig
from tflearn.plots import figures as plots

ROOT = Path(__file__).resolve().parents[1]


def run(name: str, out: Path, duration: float, step: float, amplitude) -> dict:
    cfg = config.load(ROOT / "configs" / "modes" / f"{name}.yaml", schema=ModesConfig)
    modes = modal.analyse_config(cfg)
    drives = [mm.ModeDrive(**d.model_dump()) for d in cfg.motion.drives]
    if amplitude is not None:
        drives = [replace(d, amplitude=amplitude) for d in drives]
    constraints = [md.Constraint.from_config(c.model_dump()) for c in cfg.constraints]
    base = lo.LocomotionOptions()
    opts = replace(base, duration=duration,
                   sim=replace(base.sim, solver_options={"step_size": step}))
    start = time.time()
    gait = lo.locomote(modes, drives, constraints, options=opts)
    seconds = time.time() - start
    res = {"creature": name, "drives": [asdict(d) for d in drives],
           "speed_body_lengths_per_s": gait.speed, "distance_m": gait.distance,
           "body_length_m": gait.body_length, "direction_xy": gait.direction.tolist(),
           "positive_joint_work_J": gait.work, "cost_of_transport": gait.cost_of_transport,
           "evals": gait.evals, "seconds": seconds,
           "com_height_m": [float(gait.com[:, 2].min()), float(gait.com[:, 2].max())],
           "com_lateral_max_m": float(abs(gait.com[:, 1] - gait.com[0, 1]).max()),
           "options": {"duration": duration, "settle": opts.settle, "step": step,
                       "damping": opts.damping, "ground": asdict(opts.ground),
                       "closure_stiffness": opts.closure_stiffness,
                       "closure_damping": opts.closure_damping}}
    (out / name).mkdir(parents=True, exist_ok=True)
    (out / name / "locomotion.json").write_text(json.dumps(res, indent=1))
    traj = gait.trajectory
    plots.side_view_gif(gait.body, traj.t.numpy(), traj.q, out / name / f"{name}.gif", fps=25,
                        title=name, com=gait.com)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="+")
    ap.add_argument("--out", default="runs/locomotion")
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--step", type=float, default=5e-4, help="RK4 step (s)")
    ap.add_argument("--amplitude", type=float, default=None,
                    help="α of every drive (rad); default the config's")
    args = ap.parse_args()
    torch.set_num_threads(1)
    for name in args.names:
        res = run(name, Path(args.out), args.duration, args.step, args.amplitude)
        print(json.dumps({k: v for k, v in res.items() if k != "options"}))


if __name__ == "__main__":
    main()
