"""Figures of a mocap run for the docs: per chosen motion, the recorded window (target)
against its simulation under the run's basis — a sheet of joint paths with the 3-D hand
path, and a stick-figure strip — written as MOTION.png and MOTION_strip.png.

    PYTHONPATH=. python bench/mocap_figures.py RUN --out docs/mocap [--motions TEXT...]

RUN is a training run folder (bench/mocap_basis.py writes OUT/run). With ``torso: moving``
the arm is simulated on its torso and drawn in the torso's frame (the shoulder fixed).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tflearn.data.loading import load_motions, torsos  # noqa: E402
from tflearn.evaluate import run_config, weights_for  # noqa: E402
from tflearn.experiments.common import sheets  # noqa: E402
from tflearn.fit.targets import prepare, simulate_targets  # noqa: E402
from tflearn.io import basis as basis_io  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--motions", nargs="*", default=None,
                   help="only the motions whose names contain one of these (default: all)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    lb = basis_io.load(args.run / "basis.json")
    cfg, options = run_config(args.run)
    motions = [m for m in load_motions(cfg.data, lb.body)
               if args.motions is None or any(s in m.name for s in args.motions)]
    tg = prepare(lb.body, motions, weight=cfg.solver.torque_weight, base=torsos(cfg.data, motions, cfg.torso))
    with torch.no_grad():
        q, _ = simulate_targets(lb.body, lb.basis, weights_for(lb, tg), tg, options)
    args.out.mkdir(parents=True, exist_ok=True)
    for path in sheets(lb.body, tg, {"simulated": q}, args.out):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
