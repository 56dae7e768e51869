"""Convergent pairs with a stiffness about the path on keyframe animations no field made.

For each seed, ``--motions`` eased three-key animations through random postures
(:func:`tflearn.data.keyframes.random_keyframes`, 100 Hz) are trained with
configs/convergent.yaml (antagonist pairs inside joint space, weights by NNLS on the
torques and the stiffness ω = 10 rad/s about the path, multiple shooting only on motions
the NNLS leaves unreproduced), once with fewer weights (``sparsity=0.01``, no shooting:
the NNLS alone) and once with the stiffness off (``frequency=0``, torque matching alone on
the same fields), with joint simplices instead of pairs (``joints``: b + 1 fields per joint of
b coordinates, the stiffness asked of a simplex weighted by δ/3,
:func:`tflearn.fit.impedance.free_share`; ``joints, 12 fields``: the most anisotropic
joints paired within a budget of 12, ``solver.layout.fields``), and once with fewer weights
and multiple shooting on their support (``sparsity=0.01``, ``solver.shooting.sparse``:
the zero weights held at 0), also with windows sized by each motion's length
(``model.window_rate=4``), and with all weights free at 3 windows per second (also with
the hand in shooting's residuals, ``tip_weight=100``: 1 cm counts as 0.1 rad). Printed
per seed and setting: motions reproduced, the worst joint RMSE and hand-tip error, the worst
relative torque error, the fields' median stiffness about the path (rad/s,
:func:`tflearn.fit.impedance.path_stiffness`), the non-zero weights per second of motion
and the numbers per second that describe a motion (non-zero weights, its windows' onsets
and durations, its initial state; the most of any motion), the largest centre |η| of a
joint block, and the training wall time.
With ``--push``, the first seed's motions trained with ``held`` and ``joints`` (those of
``--settings``) are pushed at the hand (``tflearn perturb``:
impulses 0.025–0.2 N·s along x, y, z at 0.5 s) under the fields and under ff+pd (Yin et
al.'s feed-forward inverse dynamics plus low-gain feedback): per motion the largest ratio
of the fields' peak hand deviation to ff+pd's, and how many pushes the fields recover from
(hand back within 5 cm of its unpushed path within 1 s of the push's end).

    PYTHONPATH=. python bench/convergent.py [--seeds 1,2,3] [--motions 3] [--push] [--out DIR]
        [--settings 'held;held, sparse, shot']
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from push_sweep import sweep  # noqa: E402

from tflearn import config, train  # noqa: E402
from tflearn.data.keyframes import random_keyframes  # noqa: E402
from tflearn.fit import impedance  # noqa: E402
from tflearn.fit.targets import prepare  # noqa: E402
from tflearn.io import basis as basis_io  # noqa: E402
from tflearn.motions.motion import save  # noqa: E402

SETTINGS = {"held": [], "held, sparse": ["solver.layout.sparsity=0.01", "solver.shooting.iterations=0"],
            "held, sparse, shot": ["solver.layout.sparsity=0.01", "solver.shooting.sparse=true"],
            "held, sparse, shot, 4 windows/s": ["solver.layout.sparsity=0.01", "solver.shooting.sparse=true",
                                                "model.window_rate=4"],
            "held, 3 windows/s": ["model.window_rate=3"],
            "held, 3 windows/s, hand": ["model.window_rate=3", "solver.shooting.tip_weight=100"],
            "torques only": ["solver.layout.frequency=0"],
            "joints": ["solver.layout.shape=joints"],
            "joints, 12 fields": ["solver.layout.shape=joints", "solver.layout.fields=12"]}

#: The settings whose first-seed runs ``--push`` pushes (those held on the path by default).
PUSHED = ("held", "joints", "joints, 12 fields")


def _slug(label: str) -> str:
    """A setting's label as a folder name's part."""
    return label.replace(", ", "_").replace(" ", "_")


def make(folder: Path, seed: int, n: int) -> list:
    """n random keyframe animations of ``seed`` written to ``folder``; their motions."""
    from tflearn.physics.body import arm
    folder.mkdir(parents=True, exist_ok=True)
    motions = random_keyframes(arm(), n, seed)
    for m in motions:
        save(m, folder / f"{m.name}.npz")
    return motions


def row(run: Path, motions: list, metrics: dict, wall: float) -> dict:
    """The figures of one trained run (module docstring)."""
    lb = basis_io.load(run / "basis.json")
    tg = prepare(lb.body, motions)
    weights = lb.weights.select_motions([lb.index(n) for n in tg.names])
    stiff = impedance.path_stiffness(lb.body, lb.basis, weights, tg)
    per = [metrics["motions"][n] for n in tg.names]
    used = (weights.vector().abs() > 0).sum(-1).double()
    nonzero = used / tg.duration
    blocks = [lb.basis.eta[:, lb.body.slice(i)].detach().norm(dim=-1).max()
              for i in range(len(lb.body.links))]
    return {"reproduced": sum(bool(p["success"]) for p in per), "N": len(per),
            "rmse": max(p["rmse"] for p in per), "tip_cm": 100 * max(p["tip"] for p in per),
            "torque_err": max(p["torque_rel_rms"] for p in per),
            "stiffness": [round(float(s), 2) for s in stiff],
            "weights_per_s": float(nonzero.max()), "numbers_per_s": metrics["overall"]["numbers_per_s"],
            "max_centre": float(max(blocks)),
            "M": lb.basis.M, "wall_s": wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--motions", type=int, default=3)
    ap.add_argument("--push", action="store_true")
    ap.add_argument("--out", default="runs/bench/convergent")
    ap.add_argument("--settings", default=";".join(SETTINGS), help="labels of SETTINGS, ';'-separated")
    args = ap.parse_args()
    torch.set_num_threads(1)
    out, rows = Path(args.out), []
    for seed in [int(s) for s in args.seeds.split(",")]:
        data = out / f"keys{seed}"
        motions = make(data, seed, args.motions)
        for label in args.settings.split(";"):
            extra = SETTINGS[label]
            run = out / f"run{seed}_{_slug(label)}"
            cfg = config.load(ROOT / "configs" / "convergent.yaml", [f"data={data}", f"out={run}", *extra])
            t0 = time.perf_counter()
            metrics = train.run(cfg, restart=True)
            r = {"seed": seed, "setting": label, **row(run, motions, metrics, time.perf_counter() - t0)}
            rows.append(r)
            print(json.dumps(r), flush=True)
    result = {"rows": rows}
    if args.push:
        first = int(args.seeds.split(",")[0])
        names = [f"keys{first}_{i}" for i in range(args.motions)]
        pushed = [label for label in args.settings.split(";") if label in PUSHED]
        result["push"] = {label: sweep(out / f"run{first}_{_slug(label)}", names,
                                       out / f"push_{_slug(label)}") for label in pushed}
        print(json.dumps(result["push"], indent=1))
    (out / "convergent.json").write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
