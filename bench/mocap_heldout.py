"""Held-out clips through a frozen layout, leave-one-out: for each clip's busiest window
(as bench/mocap_basis.py cuts them), the spanning layout of configs/mocap.yaml is built
on the other windows and frozen, and the held-out window gets only its own weights and
activation windows (:func:`tflearn.evaluate.synthesize`: NNLS on its torques, then
multiple shooting where that does not reproduce it). Prints per window the joint RMSE
and the maximum hand-tip error, and writes OUT/heldout.json.

    PYTHONPATH=. python bench/mocap_heldout.py [--mocap DIR] [--out runs/mocap_heldout]
        [--window 0.8] [--rate 50] [--clips TEXT...] [--hold TEXT...] [key=value ...]   (config overrides)

A layout depends on its motions only through their mean posture and mean inertia (and
the hull it must cover), so the other windows' own weights are not needed: the basis
frozen here is exactly the one that training on them would fix.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from mocap_basis import arguments, prepare_windows  # noqa: E402

from tflearn import config, train  # noqa: E402
from tflearn.data.loading import torsos  # noqa: E402
from tflearn.evaluate import synthesize  # noqa: E402
from tflearn.fit.targets import prepare  # noqa: E402
from tflearn.io.basis import LearnedBasis  # noqa: E402
from tflearn.metrics import score  # noqa: E402
from tflearn.motions import motion as motion_mod  # noqa: E402

#: Issue 11's bar for held-out clips: joint RMSE (rad), hand tip (m).
HELD_OUT = (0.08, 0.05)


def targets(cfg, body, motions):
    """The motions' targets as training prepares them (the config's torque weights, on
    their torsos with ``torso=moving``)."""
    return prepare(body, motions, weight=cfg.solver.torque_weight, base=torsos(cfg.data, motions, cfg.torso))


def frozen_layout(cfg, body, motions) -> LearnedBasis:
    """The config's spanning layout over ``motions`` (training's layout stage,
    :func:`tflearn.train.layout_model`) with zero weights on its windows."""
    tg = targets(cfg, body, motions)
    basis, weights = train.layout_model(cfg, body, tg)
    return LearnedBasis(body, basis, weights, tg.q0, tg.qd0, tg.rate)


def main(argv=None) -> int:
    p = arguments(__doc__.split("\n\n")[0])
    p.set_defaults(out=ROOT / "runs" / "mocap_heldout", window=0.8, rate=50.0)
    p.add_argument("--hold", nargs="*", default=None,
                   help="hold out only the windows whose names contain one of these (default: each in turn)")
    p.add_argument("overrides", nargs="*")
    args = p.parse_args(argv)
    for key in ("clips", "hold"):   # key=value after --clips or --hold would be read as names
        names = getattr(args, key) or []
        args.overrides += [c for c in names if "=" in c]
        setattr(args, key, [c for c in names if "=" not in c] or None)
    torch.set_num_threads(1)
    report, body, windows = prepare_windows(args)
    cfg = config.load(ROOT / "configs" / "mocap.yaml",
                      [f"data={windows}", "body=" + json.dumps(report["body"]), *args.overrides])
    options, success = cfg.solver.path.options(), (cfg.success.rmse, cfg.success.tip)
    shoot = cfg.solver.shooting.options(cfg.model.phases == "variable")
    motions = [motion_mod.load(windows / c["file"], body) for c in report["clips"]]
    rows = {}
    print(f"\n{'held-out window':>44s}  {'rmse (rad)':>10s}  {'tip (cm)':>8s}  reproduced  "
          f"held-out bar  wall (s)")
    for j, m in enumerate(motions):
        if args.hold and not any(h in m.name for h in args.hold):
            continue
        t0 = time.time()
        lb = frozen_layout(cfg, body, motions[:j] + motions[j + 1:])
        tg = targets(cfg, body, [m])
        weights = synthesize(lb, tg, shoot, options, success, ridge=cfg.solver.ridge)
        s = score(body, lb.basis, weights, tg, options)
        ok, bar = (bool(s.succeeded(*b)[0]) for b in (success, HELD_OUT))
        rows[m.name] = {"rmse": float(s.rmse[0]), "tip": float(s.tip[0]), "success": ok,
                        "held_out_bar": bar, "wall_s": time.time() - t0}
        r = rows[m.name]
        print(f"{m.name:>44s}  {r['rmse']:10.4f}  {100 * r['tip']:8.2f}  {'yes' if ok else 'no':>10s}  "
              f"{'yes' if bar else 'no':>12s}  {r['wall_s']:8.0f}", flush=True)
    for key, (rmse, tip) in (("success", success), ("held_out_bar", HELD_OUT)):
        print(f"M = {lb.basis.M}; {sum(r[key] for r in rows.values())} of {len(rows)} held-out windows "
              f"within {rmse:g} rad and {100 * tip:g} cm")
    (args.out / "heldout.json").write_text(json.dumps(
        {"windows": rows, "M": lb.basis.M, "overrides": args.overrides}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
