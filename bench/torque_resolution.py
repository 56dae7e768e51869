"""How well :func:`tflearn.motions.spline.torque_resolution` estimates the error of spline torques.

Draws random programs within :data:`tflearn.data.gestures.SUPPORTED`, simulates them and
samples them at ``--rate``; for each motion compares the estimate (from the samples
alone) with the true relative RMS error of the spline torques (the generating program's
torques along the path against the inverse-dynamics torques, the fit's own measure,
:func:`tflearn.fit.torque.relative_rms_torque_error`).

    python bench/torque_resolution.py --count 40 --seed 11 --rate 100
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tflearn.data import gestures
from tflearn.fit import targets, torque
from tflearn.motions import spline
from tflearn.physics.body import arm


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=40)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--rate", type=float, default=100.0)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    body = arm()
    programs = gestures.random_gestures(args.count, seed=args.seed)
    rows = []
    for motion, lb in gestures.generate(body, args.rate, gestures=programs):
        tg = targets.prepare(body, [motion])
        true = float(torque.relative_rms_torque_error(lb.basis, lb.weights, tg)[0])
        rows.append((true, spline.torque_resolution(body, motion), motion.name))
    print("| motion | true error | estimate | estimate / true |\n|---|---|---|---|")
    for true, est, name in sorted(rows):
        print(f"| {name} | {true:.2e} | {est:.2e} | {est / true:.2f} |")
    ratios = [est / true for true, est, _ in rows]
    above = sum(est > spline.RESOLVED for _, est, _ in rows)
    print(f"\nestimate / true in [{min(ratios):.2f}, {max(ratios):.2f}]; "
          f"{above} of {len(rows)} motions above RESOLVED = {spline.RESOLVED:g} at {args.rate:g} Hz")
    return 0


if __name__ == "__main__":
    sys.exit(main())
