"""How precise a planted library's fields must be for its motions to be reproduced on them.

N random programs whose fields come from G shared ones (``make`` of ``bench/learn_many.py``),
then, on the planted fields themselves rather than learned ones (configs/many.yaml's
simulation, shooting and success bar):

1. ``planted``: each motion's generating program as it is, simulated as training scores
   a fit;
2. ``exact``: the G planted fields as the basis, every motion's weights by NNLS on its
   torques, then multiple shooting of the weights of the motions those leave unreproduced;
3. ``moved``: the same with every centre moved by d rad in a random direction (``--moves``);
4. ``em``: the G fields refitted from the planted ones by torque EM over all motions
   (:func:`tflearn.fit.torque.em`): how far the torque cost's own optimum lies from them
   (the bias of the spline torques), then (2) on those fields.

Each row: motions reproduced by the NNLS weights and after shooting, the motions left
unreproduced, seconds. Prints JSON. One torch thread.

    python bench/planted_precision.py --size 300 --library 8 --moves 0.002,0.0002
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path


def _context(data: Path):
    from tflearn import config
    from tflearn.physics.body import from_config
    from tflearn.train import pipeline
    cfg = config.load(Path(__file__).resolve().parents[1] / "configs" / "many.yaml",
                      [f"data={data}", "solver.method=pipeline", "log.tensorboard=false"])
    body = from_config(cfg.body)
    tg = pipeline.load(cfg, body)[0]
    return cfg, body, tg, pipeline.new_context(cfg, tg)


def planted_fields(data: Path, names: list, template):
    """The distinct fields of the motions' generating programs (NAME.json), as one basis."""
    import torch

    from tflearn.io import basis as basis_io
    eta, K, seen = [], [], set()
    for name in names:
        b = basis_io.load(data / f"{name}.json").basis
        for e, k in zip(b.eta, b.K()):
            key = tuple(e.tolist())
            if key not in seen:
                seen.add(key)
                eta.append(e)
                K.append(k)
    return template.like(torch.stack(eta), torch.stack(K))


def as_generated(data: Path, cfg, body, tg, options) -> list:
    """The motions their own generating programs do not reproduce."""
    from tflearn.io import basis as basis_io
    from tflearn.metrics import score
    lost = []
    for j, name in enumerate(tg.names):
        lb = basis_io.load(data / f"{name}.json")
        one = tg.select([j])
        lb.weights.duration.copy_(one.duration)
        s = score(body, lb.basis, lb.weights, one, options)
        if not s.succeeded(cfg.success.rmse, cfg.success.tip)[0]:
            lost.append(name)
    return lost


def on_fields(cfg, body, tg, options, basis) -> dict:
    """NNLS weights of every motion on ``basis``, then shooting of those it leaves unreproduced."""
    from tflearn import synthesis
    from tflearn.fit import torque
    from tflearn.model.weights import MotionWeights
    t0 = time.perf_counter()
    w = MotionWeights.zeros(basis.M, tg.duration, tg.names)
    torque.solve_weights(basis, w, tg)
    bar = (cfg.success.rmse, cfg.success.tip)
    todo = synthesis.unreproduced(body, basis, w, tg, options, bar, range(tg.N))[0]
    nnls = tg.N - len(todo)
    synthesis.shoot(body, basis, w, tg, todo, cfg.solver.shooting.options(False), options)
    left = synthesis.unreproduced(body, basis, w, tg, options, bar, todo)[0] if todo else []
    return {"nnls": nnls, "shot": tg.N - len(left), "left": [tg.names[j] for j in left],
            "seconds": time.perf_counter() - t0}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=300)
    p.add_argument("--library", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--moves", default="0.002,0.0002", help="centre moves d (rad), comma-separated")
    p.add_argument("--data", type=Path, help="motions made before (make's NAME.npz and NAME.json)")
    args = p.parse_args(argv)
    import torch
    from learn_many import make

    from tflearn.fit import torque
    from tflearn.model.weights import MotionWeights
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            data = Path(tmp)
            make(args.size, args.seed, data, library=args.library)
        cfg, body, tg, ctx = _context(data)
        basis = planted_fields(data, tg.names, ctx.template())
        out = {"N": tg.N, "G": basis.M,
               "planted_not_reproducing": as_generated(data, cfg, body, tg, ctx.options),
               "exact": on_fields(cfg, body, tg, ctx.options, basis)}
        gen = torch.Generator().manual_seed(args.seed)
        for d in (float(x) for x in args.moves.split(",") if x):
            step = torch.randn(basis.eta.shape, generator=gen, dtype=torch.float64)
            moved = ctx.template().like(basis.eta + d * step / step.norm(dim=1, keepdim=True), basis.K())
            out[f"moved {d:g} rad"] = on_fields(cfg, body, tg, ctx.options, moved)
        fit = ctx.template().like(basis.eta.clone(), basis.K().clone())
        torque.em(fit, MotionWeights.zeros(fit.M, tg.duration, tg.names), tg, steps=100, tol=1e-12)
        far = (fit.eta - basis.eta).detach().norm(dim=1)
        rel = ((fit.K() - basis.K()).flatten(1).norm(dim=1) / basis.K().flatten(1).norm(dim=1)).detach()
        out["em"] = {"centre_moved_rad_max": float(far.max()), "centre_moved_rad_median": float(far.median()),
                     "stiffness_moved_max": float(rel.max()), **on_fields(cfg, body, tg, ctx.options, fit)}
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
