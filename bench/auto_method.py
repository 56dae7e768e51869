"""What ``solver.method: auto`` sees: the probe's relative torque cost on classes of motion.

Each motion of each class is searched alone on torques, as the probe does
(:func:`tflearn.train.choice.probed`, configs/gestures.yaml's search settings,
``solver.each.max_fields`` fields, no simulation); printed per class: the motions, the
smallest, median and largest cost, and how many are within the bar. Classes: the
built-in gestures; planted programs (``bench/learn_many.py``'s generator) of ten seeds,
G ∈ {0 (every program its own fields), 3, 5, 8, 12}, scalar and diagonal stiffness, ten
motions each; eased keyframe splines through random postures
(:func:`tflearn.data.keyframes.random_keyframes`) with 2–5 keys and spreads of 0.2–1.2
rad, five motions each; experiment 3's six keyframed motions; and with ``--mocap DIR``,
the busiest 0.8 s of every BVH clip there (50 Hz, the arm that moves, on its torso).

    PYTHONPATH=. python bench/auto_method.py [--mocap ../shared/data/mocap]
"""
from __future__ import annotations

import argparse
import time

import torch


def classes(mocap: str | None) -> dict:
    """{class: (config overrides, motions or None: the data the overrides name)}."""
    from tflearn.data import gestures
    from tflearn.data.keyframes import random_keyframes
    from tflearn.experiments.keyframes import keyframe_motions
    from tflearn.physics.body import arm
    body = arm()
    out = {"gestures": ([], [m for m, _ in gestures.generate(body)])}
    made = []
    for seed in range(20, 30):
        made += [m for m, _ in gestures.generate_resolved(gestures.random_gestures(
            10, seed=seed, library=(0, 3, 5, 8, 12)[seed % 5], stiffness=("diag", "scalar")[seed % 2]))]
    out["planted, 10 seeds"] = ([], made)
    splines = []
    for seed, keys, spread in ((40, 2, 0.8), (41, 3, 0.4), (42, 3, 1.2), (43, 4, 0.8), (44, 5, 0.8),
                               (45, 2, 0.3), (46, 3, 0.2)):
        splines += random_keyframes(body, 5, seed=seed, keys=keys, spread=spread)
    out["splines, 2-5 keys"] = ([], splines)
    out["experiment 3"] = ([], keyframe_motions(body, list(gestures.GESTURES)))
    if mocap:
        out["recorded windows"] = ([f"data={mocap}", "bvh.arm=moving", "bvh.rate=50", "bvh.busiest=0.8",
                                    "torso=moving", "'bvh.clips={cmu_141_16_wave-hello: {fps: 60}}'",
                                    "out=runs/bench/auto_method"], None)
    return out


def costs(overrides: list, motions) -> dict:
    """{name: the probe's cost} of every motion of one class."""
    from tflearn import config
    from tflearn.fit.targets import prepare
    from tflearn.mocap import clips
    from tflearn.physics.body import from_config
    from tflearn.train.choice import probed
    from tflearn.train.pipeline import load
    cfg = config.load("configs/gestures.yaml", [o.strip("'") for o in overrides])
    if motions is None:
        cfg = clips.import_config(cfg)[0]
        body = from_config(cfg.body)
        tg = load(cfg, body)[0]
    else:
        body = from_config(cfg.body)
        tg = prepare(body, motions)
    return probed(cfg.replace(solver={"auto": {"probes": tg.N}}), body, tg)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mocap", default=None, help="a folder of BVH clips (their busiest 0.8 s)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    from tflearn import config
    tol = config.load("configs/gestures.yaml").solver.auto.tol
    print(f"{'class':<20} {'motions':>7} {'smallest':>9} {'median':>9} {'largest':>9}  within {tol:g}")
    for name, (overrides, motions) in classes(args.mocap).items():
        t0 = time.perf_counter()
        c = sorted(costs(overrides, motions).values())
        print(f"{name:<20} {len(c):>7} {c[0]:>9.1e} {c[len(c) // 2]:>9.1e} {c[-1]:>9.1e}  "
              f"{sum(x <= tol for x in c)} ({time.perf_counter() - t0:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
