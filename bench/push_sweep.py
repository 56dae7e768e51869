"""The perturbation page's sweep of pushes on a trained run's motions: impulses 0.025–0.2
N·s along x, y and z at the hand, a 0.1 s pulse at ``--at`` seconds (``tflearn perturb``;
on a run trained on moving torsos, on each motion's torso, the pushes in the chest's
frame), under the learned fields and under ff+pd (Yin et al.'s feed-forward inverse
dynamics plus low-gain feedback). Printed per motion: the largest ratio of the fields'
peak hand deviation to ff+pd's over the pushes, both peaks, and how many pushes each
recovers from (hand back within 5 cm of its unpushed path within 1 s of the push's end;
a motion that ends sooner counts the pushes it is back from by its end).

    PYTHONPATH=. python bench/push_sweep.py RUN [--motions NAME...] [--at 0.5] [--out DIR]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tflearn import config  # noqa: E402
from tflearn.control import recovery  # noqa: E402
from tflearn.io import basis as basis_io  # noqa: E402

CONTROLLERS = ("fields", "ff+pd")


def recovered(cases: list) -> int:
    """The pushes a controller is back from within 1 s (recovery_s; None: not back)."""
    return sum(c["recovery_s"] is not None and c["recovery_s"] <= 1.0 for c in cases)


def sweep(run: Path, names: list, out: Path, at: float = 0.5) -> dict:
    """Fields against ff+pd under the sweep of pushes (module docstring)."""
    cfg = config.PerturbConfig(model=str(run), motions=names, controllers=list(CONTROLLERS),
                               sweep={"directions": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
                                      "impulses": [0.025, 0.05, 0.1, 0.2], "at": at,
                                      "duration": 0.1, "point": "hand"},
                               tol=0.05, out=str(out), animation=False, tensorboard=False)
    doc = recovery.run(cfg, progress=False)
    summary = {}
    for name, per in doc["motions"].items():
        f, p = per["fields"]["cases"], per["ff+pd"]["cases"]
        summary[name] = {
            "worst_ratio": max(a["max_hand_dev"] / b["max_hand_dev"] for a, b in zip(f, p)),
            "fields_peak_cm": 100 * max(a["max_hand_dev"] for a in f),
            "ffpd_peak_cm": 100 * max(b["max_hand_dev"] for b in p),
            "recovered_1s": recovered(f), "ffpd_recovered_1s": recovered(p), "cases": len(f)}
    return summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--motions", nargs="*", default=None, help="default: every motion of the run")
    ap.add_argument("--at", type=float, default=0.5, help="push onset, s (default 0.5)")
    ap.add_argument("--out", type=Path, default=None, help="default RUN/push_sweep")
    args = ap.parse_args()
    torch.set_num_threads(1)
    names = args.motions or basis_io.load(args.run / "basis.json").names
    out = args.out or args.run / "push_sweep"
    summary = sweep(args.run, names, out, args.at)
    print(f"{'motion':>44s}  {'worst ratio':>11s}  {'fields (cm)':>11s}  {'ff+pd (cm)':>10s}  "
          f"recovered fields / ff+pd")
    for name, s in summary.items():
        print(f"{name:>44s}  {s['worst_ratio']:11.2f}  {s['fields_peak_cm']:11.2f}  {s['ffpd_peak_cm']:10.2f}"
              f"  {s['recovered_1s']:2d} / {s['ffpd_recovered_1s']:2d} of {s['cases']}")
    total = {k: sum(s[k] for s in summary.values()) for k in ("recovered_1s", "ffpd_recovered_1s", "cases")}
    print(f"all: worst ratio {max(s['worst_ratio'] for s in summary.values()):.2f}, fields recovered "
          f"{total['recovered_1s']} of {total['cases']}, ff+pd {total['ffpd_recovered_1s']}")
    (out / "push_sweep.json").write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
