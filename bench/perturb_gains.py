"""Recovery of ff+pd against its gains (docs/perturbation.md): the pushes of
configs/perturb.yaml (no sweep) under K = s·K₀ (+ c|τ_ff|), B = √s·B₀.

    python bench/perturb_gains.py [--config configs/perturb.yaml] [--out runs/perturb/gains]

Prints one markdown row per motion and gain setting.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from tflearn.config import PerturbConfig, load, merge, validate
from tflearn.control import recovery

SETTINGS = [(0.25, 0.0), (1.0, 0.0), (4.0, 0.0), (1.0, 5.0)]     # (scale s, bilinear c rad⁻¹)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=Path("configs/perturb.yaml"))
    ap.add_argument("--out", type=Path, default=Path("runs/perturb/gains"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    base = load(args.config, (), PerturbConfig).model_dump()
    print("| motion | s | c (rad⁻¹) | max hand dev (cm) | recovery (s) | final error (rad) | "
          "peak torque (N·m) |")
    print("|---|---|---|---|---|---|---|")
    for s, c in SETTINGS:
        cfg = validate(merge(base, {"controllers": ["ff+pd"], "sweep": {"directions": [], "impulses": []},
                                    "gains": {"scale": s, "bilinear": c}, "animation": False,
                                    "tensorboard": False, "out": str(args.out / f"s{s:g}_c{c:g}")}),
                       PerturbConfig)
        doc = recovery.run(cfg, progress=False)
        for name, res in doc["motions"].items():
            row = res["ff+pd"]["cases"][0]
            rec = "not recovered" if row["recovery_s"] is None else f"{row['recovery_s']:.2f}"
            print(f"| {name} | {s:g} | {c:g} | {100 * row['max_hand_dev']:.2f} | {rec} | "
                  f"{row['final_joint_error']:.4f} | {row['peak_torque']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
