"""Path matching of activations, the basis fixed: multiple-shooting Levenberg–Marquardt
(:func:`tflearn.fit.shooting.shooting_match`) against the safeguarded Adam baseline
(:func:`tflearn.fit.path.path_match` with ``fields=False``), from the same start.

Cases:

* ``gestures``: the five gestures of the thesis' library under their generating basis
  (:func:`tflearn.data.gestures.library_model`), every step and pulse weight multiplied by
  1 + 0.3u, u ~ U[−1, 1] (seeded): the exact answer is known (the path loss can reach 0);
* ``--basis B --motion F``: a motion file (.npz) played through the frozen basis of a
  run (e.g. a held-out reach of ``tflearn experiment reaches``), its weights first by
  NNLS on its torques, its windows placed from its data, as in
  :func:`tflearn.evaluate.synthesize`; with ``--phases`` the timing is fitted too.

Reported per method: the path loss (:func:`tflearn.fit.path.path_loss`) before and
after, the joint RMSE and maximum hand-tip error of the result
(:func:`tflearn.metrics.score`), wall time and the number of batched simulations.

    python bench/path_methods.py [--adam-steps 30] [--out runs/bench/path_methods.json]
    python bench/path_methods.py --basis RUN/basis.json --motion held.npz --phases
"""
from __future__ import annotations

import argparse
import time

import revision
import torch


def gestures_case(seed: int = 0):
    from tflearn.data import gestures
    from tflearn.fit.targets import prepare
    from tflearn.physics.body import arm
    body = arm()
    pairs = gestures.generate(body)
    basis, truth, _ = gestures.library_model(body=body)
    weights = truth.select_motions(range(truth.N))
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in (weights.a_raw, weights.b_raw):
            p.mul_(1 + 0.3 * (2 * torch.rand(p.shape, generator=g, dtype=torch.float64) - 1))
    return body, basis, weights, prepare(body, [m for m, _ in pairs])


def file_case(basis_path: str, motion_path: str):
    from tflearn.fit.targets import prepare, submovement_windows
    from tflearn.fit.torque import solve_weights
    from tflearn.io import basis as basis_io
    from tflearn.model.weights import MotionWeights
    from tflearn.motions.motion import load
    lb = basis_io.load(basis_path)
    tg = prepare(lb.body, [load(motion_path, body=lb.body)])
    weights = MotionWeights.zeros(lb.basis.M, tg.duration, tg.names,
                                  submovement_windows(tg, lb.weights.P))
    solve_weights(lb.basis, weights, tg)
    return lb.body, lb.basis, weights, tg


def measure(body, basis, weights, tg, method: str, phases: bool, adam_steps: int) -> dict:
    from tflearn.fit.path import path_loss, path_match
    from tflearn.fit.shooting import ShootingOptions, shooting_match
    from tflearn.fit.targets import simulate_targets
    from tflearn.metrics import score
    from tflearn.model.program import model_from_state, model_state
    from tflearn.simulation import simulate as sim_mod
    from tflearn.simulation.simulate import SimOptions
    basis, weights = model_from_state(model_state(basis, weights))       # a fresh copy
    for p in basis.parameters():
        p.requires_grad_(False)
    sim = SimOptions(rtol=1e-6, atol=1e-8, max_evals=20000)

    def loss():
        with torch.no_grad():
            return path_loss(body, *simulate_targets(body, basis, weights, tg, sim), tg).tolist()
    before, calls, t0 = loss(), sim_mod.calls, time.perf_counter()
    if method == "shooting":
        shooting_match(body, basis, weights, tg, options=ShootingOptions(phases=phases), sim=sim)
    else:
        path_match(body, basis, weights, tg, steps=adam_steps, lr=0.003, fields=False,
                   phases=phases, options=sim)
    wall, sims = time.perf_counter() - t0, sim_mod.calls - calls
    s = score(body, basis, weights, tg, sim)
    return {"method": method, "loss_before": before, "loss_after": loss(), "rmse": s.rmse,
            "tip_cm": [100 * x for x in s.tip], "wall_s": wall, "simulations": sims}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--basis")
    ap.add_argument("--motion")
    ap.add_argument("--phases", action="store_true")
    ap.add_argument("--adam-steps", type=int, default=30)
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    case = file_case(args.basis, args.motion) if args.basis else gestures_case()
    rows = [measure(*case, m, args.phases, args.adam_steps) for m in ("shooting", "adam")]
    for r in rows:
        print(f"{r['method']:9s} loss {sum(r['loss_before']):.3e} -> {sum(r['loss_after']):.3e}  "
              f"worst RMSE {max(r['rmse']):.4f} rad  worst tip {max(r['tip_cm']):.2f} cm  "
              f"{r['wall_s']:.0f} s  {r['simulations']} simulations")
    revision.write_json(args.out, {"case": "file" if args.basis else "gestures", "rows": rows})


if __name__ == "__main__":
    main()
