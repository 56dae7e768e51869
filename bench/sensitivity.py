"""How much a random program's path amplifies an error in its fields: each program of
``random_gestures(N, seed)`` named on the command line is generated at the rate that
resolves it (:func:`tflearn.data.gestures.generate_resolved`), then simulated from rest under
its own program with every centre moved by δ in a random direction (``--draws`` per δ,
the worst kept), rtol 1e-9; printed per program and δ: the worst joint RMSE (rad) and
hand-tip error (cm) against the unmoved motion (docs/model.md, "Programs whose motion
is chaotic").

    python bench/sensitivity.py random0_0 random0_4 random0_6 --count 10 --seed 0
"""
from __future__ import annotations

import argparse
import sys

import torch

from tflearn.data import gestures
from tflearn.fit.targets import prepare
from tflearn.metrics import score
from tflearn.model.fields import FieldBasis
from tflearn.model.weights import MotionWeights
from tflearn.physics.body import arm
from tflearn.simulation.simulate import SimOptions


def worst(body, program, tg, delta: float, draws: int, gen: torch.Generator) -> tuple:
    """(worst RMSE, worst tip) over ``draws`` centre moves of size ``delta``."""
    eta0 = torch.tensor(program.eta, dtype=torch.float64)
    K = torch.stack([k * torch.eye(eta0.shape[1], dtype=torch.float64) for k in program.k])
    out = []
    for _ in range(draws):
        d = torch.randn(eta0.shape, generator=gen, dtype=torch.float64)
        basis = FieldBasis(eta0 + delta * d / d.norm(dim=-1, keepdim=True), K, kind="diag")
        w = MotionWeights(torch.tensor([program.a]), torch.tensor([program.b]), tg.duration,
                          names=tg.names)
        s = score(body, basis, w, tg, SimOptions(rtol=1e-9, atol=1e-11, max_evals=None, batch="each"))
        out.append((s.rmse[0], s.tip[0]))
    return max(r for r, _ in out), max(t for _, t in out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("names", nargs="+")
    p.add_argument("--count", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--deltas", default="1e-6,1e-5,1e-4,1e-3")
    p.add_argument("--draws", type=int, default=4)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    body, gen = arm(), torch.Generator().manual_seed(1)
    programs = {g.name: g for g in gestures.random_gestures(args.count, seed=args.seed)}
    for name in args.names:
        (motion, _), = gestures.generate_resolved([programs[name]], body)
        tg = prepare(body, [motion])
        cells = [(float(x), *worst(body, programs[name], tg, float(x), args.draws, gen))
                 for x in args.deltas.split(",")]
        print(f"{name} ({len(programs[name].eta)} fields, {motion.rate:.0f} Hz): " + "; ".join(
            f"δ {d:g} → {r:.2g} rad, {100 * t:.2g} cm" for d, r, t in cells), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
