"""The learning bar on unseen torque-field programs, over several seeds, with the thesis'
SLSQP baseline on the same motions.

For each seed, three random programs within :data:`tflearn.data.gestures.SUPPORTED` are
simulated from rest and each sampled at the lowest of 100·2ᵏ Hz that resolves it
(:func:`tflearn.data.gestures.generate_resolved`) and written as NAME.npz with its
generating program beside it as NAME.json (:func:`tflearn.data.gestures.write`). Then

* ``pipeline`` — ``train`` with the default config (no initial guess, M found);
* ``slsqp``    — ``train ... solver.method=slsqp model.fields=G`` with G the number of
  generating fields (the thesis' method from a seeded random guess; ``--slsqp-iter``
  iterations, default 2000).

Each row: M, motions reproduced (joint RMSE ≤ 0.03 rad and tip ≤ 2 cm), the generating
fields a learned field matches (metrics.json's ``identity``, :mod:`tflearn.fit.identity`:
centre within 0.1 rad and stiffness within 20% along the directions the motions excite),
the worst joint RMSE and tip error, the worst relative RMS torque error, the largest
local error growth along a path (e-folds, :mod:`tflearn.fit.stability`) and the run's
wall time. ``--set KEY=VALUE`` passes config overrides to the pipeline's runs.

    python bench/unseen_programs.py --seeds 2024 3 5 7 11 --out unseen.json
    python bench/unseen_programs.py --methods pipeline --set solver.reduce.growth=1.0
    python bench/unseen_programs.py --stiffness diag --methods pipeline --seeds 2024 3 5 7 11
    python bench/unseen_programs.py --stiffness full --methods pipeline --seeds 2024 3 5 7 11
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tflearn import config, train  # noqa: E402
from tflearn.data import gestures  # noqa: E402
from tflearn.motions import motion as motion_mod  # noqa: E402


def run_seed(seed: int, work: Path, slsqp_iter: int, stiffness: str = "scalar",
             methods=("pipeline", "slsqp"), overrides=()) -> list:
    programs = gestures.random_gestures(3, seed=seed, stiffness=stiffness)
    fields = sum(len(p.eta) for p in programs)
    data = work / f"s{seed}" / "data"
    gestures.write(data, plots=False, gestures=programs, resolved=True)
    rates = {m.name: round(m.rate) for m in motion_mod.load_dir(data)}
    base = [f"data={data}", "log.progress=false", "log.tensorboard=false"]
    runs = {"pipeline": list(overrides),
            "slsqp": ["solver.method=slsqp", f"model.fields={fields}",
                      f"solver.slsqp.max_iter={slsqp_iter}"]}
    rows = []
    for method in methods:
        extra = runs[method]
        cfg = config.load(None, base + [f"out={work / f's{seed}' / method}"] + extra)
        metrics = train.run(cfg, restart=True)
        per = metrics["motions"].values()
        rows.append({"seed": seed, "stiffness": stiffness, "method": method, "fields": fields, "rates": rates,
                     "M": metrics["overall"]["M"],
                     "reproduced": sum(r["success"] for r in per), "motions": len(per),
                     "fields_matched": metrics["identity"]["matched"], "identity": metrics["identity"],
                     "rmse": max(r["rmse"] for r in per), "tip": max(r["tip"] for r in per),
                     "torque": max(r["torque_rel_rms"] for r in per),
                     "efolds": max(r["growth_efolds"] for r in per),
                     "wall": metrics["overall"]["wall_time_s"],
                     "per_motion": metrics["motions"]})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[2024])
    ap.add_argument("--slsqp-iter", type=int, default=2000)
    ap.add_argument("--stiffness", choices=gestures.STIFFNESS_KINDS, default="scalar",
                    help="the generating programs' stiffness (gestures.random_gestures)")
    ap.add_argument("--methods", nargs="+", choices=("pipeline", "slsqp"), default=["pipeline", "slsqp"])
    ap.add_argument("--out", type=Path, help="write every row as JSON")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="config overrides for the pipeline's runs")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    print("| seed | method | generating fields | M | reproduced | fields matched | worst RMSE (rad) "
          "| worst tip (cm) | worst torque error | largest growth (e-folds) | wall (s) |\n"
          "|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            for r in run_seed(seed, Path(tmp), args.slsqp_iter, args.stiffness, args.methods, args.set):
                rows.append(r)
                print(f"| {r['seed']} | {r['method']} | {r['fields']} | {r['M']} | "
                      f"{r['reproduced']}/{r['motions']} | {r['fields_matched']}/{r['identity']['G']} | "
                      f"{r['rmse']:.4f} | {100 * r['tip']:.2f} | "
                      f"{100 * r['torque']:.2f}% | {r['efolds']:.2f} | {r['wall']:.0f} |", flush=True)
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
