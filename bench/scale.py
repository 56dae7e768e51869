"""How the pipeline's pooled work grows with the number of motions N: the cost of one EM
step (NNLS weights for every motion + one Levenberg–Marquardt step on the shared fields)
and of scoring every motion by one batched simulation — its batch stepped together
(``SimOptions.batch`` ``shared``, torchdiffeq) and each motion on its own steps
(``each``) — for N random supported programs (:func:`tflearn.data.gestures.random_gestures`,
made by one batch of per-motion steps at rtol = atol = 1e-10 and sampled at 100 Hz), with
the fitted exponent of each (cost ∝ N^p by least squares on log–log).

The model is held fixed in size — the gesture library's M = 7 fields — so that only N
changes; the per-motion stage (``each``) fits every motion alone, so its cost is linear
in N by construction and is not repeated here. One process, one torch thread.

    python bench/scale.py --sizes 10,30,100,300,1000 --out runs/bench/scale.json
"""
from __future__ import annotations

import argparse
import json
import math
import resource
import sys
import time
from pathlib import Path

import revision
import torch

from tflearn.simulation.simulate import SimOptions, SimulationFailed


def measure(n: int, seed: int, batches: list) -> dict:
    from tflearn.data import gestures
    from tflearn.fit import torque
    from tflearn.fit.targets import prepare
    from tflearn.metrics import score
    from tflearn.model.weights import MotionWeights
    from tflearn.physics.body import arm

    body = arm()
    programs = gestures.random_gestures(n, seed=seed)
    t0 = time.perf_counter()
    making = SimOptions(rtol=1e-10, atol=1e-10, max_evals=None, batch="each")
    motions = [m for m, _ in gestures.generate(body, gestures=programs, options=making)]
    generate = time.perf_counter() - t0
    tg = prepare(body, motions)
    basis, _, _ = gestures.library_model(body=body)
    weights = MotionWeights.zeros(basis.M, tg.duration, names=tg.names)
    torque.solve_weights(basis, weights, tg)
    t0 = time.perf_counter()
    torque.em(basis, weights, tg, steps=1, tol=0.0)
    em_step = time.perf_counter() - t0
    row = {"motions": n, "samples": int(tg.mask.sum()), "generate_s": generate, "em_step_s": em_step}
    for batch in batches:
        t0 = time.perf_counter()
        try:
            scores = score(body, basis, weights, tg, SimOptions(batch=batch))
            row[f"failed_{batch}"] = sum(f is not None for f in scores.failure)
        except SimulationFailed as err:
            row[f"failed_{batch}"] = str(err)
        row[f"score_{batch}_s"] = time.perf_counter() - t0
    row["max_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return row


def exponent(rows: list, key: str) -> float:
    """p in cost ∝ N^p, least squares on log–log."""
    xs = [math.log(r["motions"]) for r in rows]
    ys = [math.log(r[key]) for r in rows]
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sum((x - mx) ** 2 for x in xs)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="10,30,100,300,1000")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch", default="shared,each",
                   help="how the scoring simulation steps its batch (SimOptions.batch), each measured")
    p.add_argument("--out", type=Path)
    args = p.parse_args(argv)
    commit = revision.head()                  # the code this process runs
    torch.set_num_threads(1)
    rows = []
    for n in (int(x) for x in args.sizes.split(",")):
        try:
            rows.append(measure(n, args.seed, args.batch.split(",")))
        except SimulationFailed as err:            # a program that cannot be made stops its size
            rows.append({"motions": n, "error": str(err)})
        print(json.dumps(rows[-1]), flush=True)
    doc = {"commit": commit, "rows": rows}
    done = [r for r in rows if "error" not in r]
    if len(done) > 1:
        keys = ["generate_s", "em_step_s"] + [k for k in done[0] if k.startswith("score_")]
        doc["exponents"] = {k: exponent(done, k) for k in keys}
        print(json.dumps(doc["exponents"]))
    revision.write_json(args.out, doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
