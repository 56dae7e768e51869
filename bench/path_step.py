"""One path-matching step — simulate every motion under its program, the path loss, and
its gradient with respect to every field and weight — for 5, 100 and 1,000 motions,
backpropagating through the solver (direct) or by the adjoint method, per solver.

The motions are the five gestures of the thesis' library repeated (copy c of gesture g
has its step and pulse weights scaled by 1 + 0.01 c, so that no two are the same), the
model is the library's generating one (:func:`tflearn.data.gestures.library_model`), and the
loss is :func:`tflearn.fit.path.path_loss` over :func:`tflearn.fit.targets.simulate_targets`
(one batched ``odeint``), as in the pipeline's path stage. Each case runs in its own
process so that its peak memory (max RSS) is its own; a case that needs more than
``--timeout`` seconds is reported as such.

    python bench/path_step.py --out runs/bench/path_step.json [--sizes 5,100,1000]
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import revision
import torch


def problem(n: int) -> tuple:
    """The gesture library repeated to n motions, weights scaled 1% per copy, with the
    library's generating fields: (body, basis, weights, targets)."""
    from tflearn.data import gestures
    from tflearn.fit.targets import prepare
    from tflearn.model.weights import MotionWeights
    from tflearn.motions.motion import Motion
    from tflearn.physics.body import arm

    body = arm()
    pairs = gestures.generate(body)
    basis, w5, _ = gestures.library_model(body=body)
    reps = -(-n // len(pairs))
    motions = [Motion(f"{m.name}_{c}", m.t, m.q, m.qd) for c in range(reps) for m, _ in pairs][:n]
    scale = torch.tensor([1 + 0.01 * c for c in range(reps) for _ in pairs], dtype=torch.float64)[:n, None]
    idx = [j % len(pairs) for j in range(n)]
    weights = MotionWeights(w5.a[idx] * scale, w5.b[idx] * scale, w5.duration[idx],
                            names=[m.name for m in motions])
    return body, basis, weights, prepare(body, motions)


def one_case(n: int, method: str, adjoint: bool) -> dict:
    from tflearn.fit.path import path_loss
    from tflearn.fit.targets import simulate_targets
    from tflearn.simulation.simulate import SimOptions

    torch.set_num_threads(1)
    body, basis, weights, tg = problem(n)
    options = SimOptions(method=method, adjoint=adjoint)
    t0 = time.perf_counter()
    q_sim, v_sim = simulate_targets(body, basis, weights, tg, options)
    loss = path_loss(body, q_sim, v_sim, tg).sum()
    forward = time.perf_counter() - t0
    loss.backward()
    total = time.perf_counter() - t0
    grads = [p.grad for p in (*basis.parameters(), *weights.parameters()) if p.grad is not None]
    return {"motions": n, "method": method, "adjoint": adjoint, "forward_s": forward,
            "step_s": total, "loss": float(loss),
            "gradient_norm": float(torch.sqrt(sum((g ** 2).sum() for g in grads))),
            "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path)
    p.add_argument("--sizes", default="5,100,1000")
    p.add_argument("--methods", default="dopri5,dopri8")
    p.add_argument("--timeout", type=float, default=900.0)
    p.add_argument("--case", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.case:
        n, method, adjoint = args.case.split(",")
        print(json.dumps(one_case(int(n), method, adjoint == "adjoint")))
        return 0
    rows = []
    for n in (int(x) for x in args.sizes.split(",")):
        for method in args.methods.split(","):
            for mode in ("direct", "adjoint"):
                case = f"{n},{method},{mode}"
                try:
                    res = subprocess.run([sys.executable, __file__, "--case", case], check=True,
                                         capture_output=True, text=True, timeout=args.timeout)
                    rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
                except subprocess.TimeoutExpired:
                    rows.append({"motions": n, "method": method, "adjoint": mode == "adjoint",
                                 "timeout_s": args.timeout})
                except subprocess.CalledProcessError as err:
                    rows.append({"motions": n, "method": method, "adjoint": mode == "adjoint",
                                 "error": err.stderr.strip().splitlines()[-1][:200]})
                print(json.dumps(rows[-1]), flush=True)
    revision.write_json(args.out, {"rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
