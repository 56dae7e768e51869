"""The local error growth rate λ(t) along motions' paths under the bases of several runs,
drawn one panel per motion (tflearn.fit.stability; docs/model.md, "Error growth along
the path").

    tflearn train configs/gestures.yaml out=runs/gestures
    tflearn train configs/gestures.yaml out=runs/gestures-g1 solver.reduce.growth=1.0
    python bench/growth.py runs/gestures runs/gestures-g1 --labels default growth=1 \\
        --motions come_here stiff_elbow_lift planar_line --out docs/results/growth.png

Each run is a ``train`` output folder (basis.json, config.yaml); its motions are read
from the run's data, prepared as the run prepared them (torque weight, torso), and
linearised about their recorded paths under the run's weights. Prints each motion's peak
rate and e-folds per run.
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
from tflearn.fit import stability  # noqa: E402
from tflearn.fit.targets import prepare  # noqa: E402
from tflearn.io import basis as basis_io  # noqa: E402
from tflearn.plots import figures as plots  # noqa: E402


def run_growth(run: Path, names) -> tuple:
    """(targets, growth) of the motions ``names`` (None: all) under a run's basis."""
    lb = basis_io.load(run / "basis.json")
    cfg, _ = run_config(run)
    motions = [m for m in load_motions(cfg.data, lb.body, strict=cfg.strict)
               if names is None or m.name in names]
    tg = prepare(lb.body, motions, weight=cfg.solver.torque_weight,
                 base=torsos(cfg.data, motions, cfg.torso))
    return tg, stability.growth(lb.body, lb.basis, weights_for(lb, tg), tg)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--labels", nargs="+", help="one per run (default: the folders' names)")
    ap.add_argument("--motions", nargs="+", help="default: every motion of the first run")
    ap.add_argument("--out", type=Path, required=True, help="the figure (.png)")
    args = ap.parse_args(argv)
    labels = args.labels or [r.name for r in args.runs]
    if len(labels) != len(args.runs):
        ap.error("--labels: one label per run")
    torch.set_num_threads(1)
    results = [run_growth(r, args.motions) for r in args.runs]
    names = results[0][0].names
    fig, axes = plots.plt.subplots(len(names), 1, figsize=(7, 2.2 * len(names)), squeeze=False)
    for ax, name in zip(axes[:, 0], names):
        for label, (tg, g) in zip(labels, results):
            j = tg.names.index(name)
            ax.plot(tg.t[j][tg.mask[j]], g.rate[j][tg.mask[j]],
                    label=f"{label}: peak {float(g.peak[j]):.1f} /s, {float(g.efolds[j]):.2f} e-folds")
            print(f"{name:>24s}  {label:>12s}  peak {float(g.peak[j]):7.2f} /s  "
                  f"e-folds {float(g.efolds[j]):6.2f}")
        ax.axhline(0.0, color="0.6", lw=0.8)
        ax.set_title(name, fontsize=9)
        ax.set_ylabel("λ (1/s)")
        ax.legend(fontsize=7)
    axes[-1, 0].set_xlabel("t (s)")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    plots.save(fig, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
