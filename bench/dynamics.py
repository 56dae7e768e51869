"""Dynamics throughput and small-batch latency: tflearn against Pinocchio on the same states.

For the 7-DOF arm (float64, one torch thread), per sample:

* inverse dynamics (RNEA), forward dynamics (tflearn: the articulated-body algorithm;
  Pinocchio: ``aba``) and the mass matrix (tflearn: RNEA columns; Pinocchio: ``crba``)
  at batches 1 … 10⁶, against a Pinocchio call from Python (a loop over states) and
  Pinocchio's C++ batch loops ``rneaInParallel`` / ``abaInParallel`` on one thread (the
  cost of the compiled algorithm itself, without Python);
* the same two with a gradient to carry (q requires grad: torch's recursions, what path
  matching differentiates; without one, tflearn runs them compiled, :mod:`tflearn.physics.kernels`);
* one right-hand side of the arm's ODE (:class:`tflearn.simulation.simulate.ArmODE`, batch 1, a
  gesture's field program, no gradient) and a 3 s gesture simulated at the default
  tolerances (:class:`tflearn.simulation.simulate.SimOptions`), and the same gesture stepped alone
  (batch ``each``) by the compiled simulator (:mod:`tflearn.simulation.simkernel`), whose time per
  right-hand side includes its solver;
* how many ATen operators each of those dispatches at batch 1 (the profile that
  explains small-batch latency);
* with ``--ref REV`` the tflearn figures are measured again, in a subprocess, for the
  package as it was at git revision REV (a temporary worktree), so that before/after
  ratios come from one invocation.

Every figure is the best of three repeats of a loop lasting at least ``--min-time``
seconds. Writes JSON (``--out``); ``bench/benchmarks.py`` turns it into
docs/benchmarks.md.

    python bench/dynamics.py --out runs/bench/dynamics.json [--ref 607d0dd] [--max-batch 1000000]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np
import revision
import torch

ROOT = Path(__file__).resolve().parents[1]
BATCHES = [1, 10, 100, 1_000, 10_000, 100_000, 1_000_000]


def best_time(fn, min_time: float) -> float:
    """Seconds per call: the best of three loops of at least ``min_time`` seconds each."""
    fn()
    n, best = 1, float("inf")
    for _ in range(3):
        while True:
            t0 = time.perf_counter()
            for _ in range(n):
                fn()
            dt = time.perf_counter() - t0
            if dt >= min_time:
                break
            n = max(2 * n, int(n * 1.2 * min_time / max(dt, 1e-9)))
        best = min(best, dt / n)
    return best


def aten_ops(fn) -> int:
    """How many ATen operators one call dispatches (torch.profiler): at small batches
    each costs a roughly fixed overhead, so this count is what bounds latency."""
    from torch.profiler import profile
    fn()
    with profile() as prof:
        fn()
    return sum(e.count for e in prof.key_averages() if e.key.startswith("aten::"))


def states(nv: int, batch: int, seed: int = 0):
    """Random states: rotation vectors of angle < π, velocities and accelerations N(0, 1)."""
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(batch, nv, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True).clamp(min=1.0) * 2.0
    return q, torch.randn(batch, nv, generator=g, dtype=torch.float64), \
        torch.randn(batch, nv, generator=g, dtype=torch.float64)


def tflearn_figures(max_batch: int, min_time: float) -> dict:
    """Seconds per call of tflearn's algorithms, the RHS and a gesture simulation."""
    from tflearn.data import gestures
    from tflearn.model.program import FieldProgram
    from tflearn.physics import dynamics
    from tflearn.physics.body import arm
    from tflearn.physics.configspace import pack
    from tflearn.simulation import simulate as sim

    body = arm()
    out = {"rnea": {}, "forward": {}, "mass": {}}
    with torch.no_grad():
        for B in (b for b in BATCHES if b <= max_batch):
            q, v, a = states(body.nv, B)
            out["rnea"][B] = best_time(partial(dynamics.rnea, body, q, v, a), min_time)
            out["forward"][B] = best_time(partial(dynamics.forward_dynamics, body, q, v, a), min_time)
            if B <= max_batch // 10:                  # M: nv RNEA columns, 10× the memory
                out["mass"][B] = best_time(partial(dynamics.mass_matrix, body, q), min_time)
        motion, lb = gestures.generate(body)[0]
        program = FieldProgram(lb.basis, lb.weights)
        rhs = sim.ArmODE(body, program)
        y = pack(body, motion.q[:1] + 0.1, motion.qd[:1] + 0.1)
        t = torch.tensor(0.5, dtype=torch.float64)
        out["rhs_batch1"] = best_time(lambda: rhs(t, y), min_time)
        q, v, a = states(body.nv, 1)
        out["aten_ops_batch1"] = {"rhs": aten_ops(lambda: rhs(t, y)),
                                  "forward": aten_ops(lambda: dynamics.forward_dynamics(body, q, v, a)),
                                  "rnea": aten_ops(lambda: dynamics.rnea(body, q, v, a))}

        def gesture():
            return sim.simulate(body, program, lb.q0, lb.qd0, motion.t, sim.SimOptions())
        evals = []
        orig = sim.ArmODE.forward

        def counting(self, t, y):
            evals.append(1)
            return orig(self, t, y)
        sim.ArmODE.forward = counting
        gesture()
        sim.ArmODE.forward = orig
        out["gesture"] = {"name": motion.name, "duration_s": float(motion.t[-1]),
                          "rhs_evals": len(evals), "seconds": best_time(gesture, min_time)}
        try:                                  # the compiled simulator (tflearn.simulation.simkernel)
            from tflearn.simulation import simkernel
        except ImportError:                   # a revision from before it
            simkernel = None
        if simkernel is not None:
            each = sim.SimOptions(batch="each")
            y0 = pack(body, lb.q0, lb.qd0)
            sol = simkernel.integrate(body, program, y0, motion.t, rtol=each.rtol, atol=each.atol,
                                      max_evals=each.max_evals)
            out["gesture_compiled"] = {
                "rhs_evals": int(sol.evals.sum()),
                "seconds": best_time(lambda: sim.simulate(body, program, lb.q0, lb.qd0, motion.t, each),
                                     min_time)}
    out["grad"] = {"rnea": {}, "forward": {}}            # q needs a gradient: torch's recursions
    for B in (b for b in BATCHES if b <= max_batch // 10):
        q, v, a = states(body.nv, B)
        q.requires_grad_()
        out["grad"]["rnea"][B] = best_time(partial(dynamics.rnea, body, q, v, a), min_time)
        out["grad"]["forward"][B] = best_time(partial(dynamics.forward_dynamics, body, q, v, a), min_time)
    return out


def pinocchio_figures(max_batch: int, min_time: float) -> dict:
    """Seconds per call of Pinocchio from Python, and per sample of its C++ batch loops
    (one thread) at each batch size."""
    import pinocchio as pin
    from validate_physics import q_pin, to_pin

    from tflearn.physics.body import arm

    body = arm()
    model = to_pin(body)
    data = model.createData()
    q, v, a = (x.numpy() for x in states(body.nv, 256))
    qp = np.stack([q_pin(body, qi) for qi in q])
    k = [0]

    def one(f):
        def call():
            i = k[0] = (k[0] + 1) % len(qp)
            f(model, data, qp[i], v[i], a[i])
        return call
    out = {"python": {"rnea": best_time(one(pin.rnea), min_time),
                      "aba": best_time(one(pin.aba), min_time),
                      "crba": best_time(one(lambda m, d, q_, v_, a_: pin.crba(m, d, q_)), min_time)},
           "batch": {"rnea": {}, "aba": {}}}
    pool = pin.ModelPool(model, 1)
    for B in (b for b in BATCHES if b <= max_batch):
        reps = -(-B // len(qp))
        Q = np.asfortranarray(np.tile(qp, (reps, 1))[:B].T)
        V = np.asfortranarray(np.tile(v, (reps, 1))[:B].T)
        A = np.asfortranarray(np.tile(a, (reps, 1))[:B].T)
        res = np.zeros((model.nv, B), order="F")
        out["batch"]["rnea"][B] = best_time(partial(pin.rneaInParallel, 1, pool, Q, V, A, res), min_time) / B
        out["batch"]["aba"][B] = best_time(partial(pin.abaInParallel, 1, pool, Q, V, A, res), min_time) / B
    return out


def at_revision(rev: str, args) -> dict:
    """tflearn_figures for the package at git revision ``rev`` (a temporary worktree, this
    script run there in a subprocess with that tree first on the path)."""
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), rev],
                       check=True, capture_output=True)
        try:
            out = Path(tmp) / "ref.json"
            env = {**os.environ, "PYTHONPATH": str(tree)}
            subprocess.run([sys.executable, __file__, "--tflearn-only", "--out", str(out),
                            "--max-batch", str(args.ref_max_batch), "--min-time", str(args.min_time)],
                           check=True, env=env, cwd=tree)
            return json.loads(out.read_text())["tflearn"]
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                           check=True, capture_output=True)


def machine() -> dict:
    return {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
            "python": platform.python_version(), "torch": torch.__version__,
            "torch_threads": torch.get_num_threads()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--ref", help="git revision to measure tflearn at as well")
    p.add_argument("--max-batch", type=int, default=1_000_000)
    p.add_argument("--ref-max-batch", type=int, default=100_000,
                   help="the reference revision's largest batch (its forward dynamics held "
                        "nv + 1 RNEA columns: 8× the memory)")
    p.add_argument("--min-time", type=float, default=0.2)
    p.add_argument("--tflearn-only", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    doc = {"machine": machine(), "tflearn": tflearn_figures(args.max_batch, args.min_time)}
    if not args.tflearn_only:
        import pinocchio as pin
        doc["pinocchio"] = {"version": pin.__version__,
                            **pinocchio_figures(args.max_batch, args.min_time)}
        doc["commit"] = revision.head()
        if args.ref:
            doc["reference"] = {"rev": args.ref, "tflearn": at_revision(args.ref, args)}
    revision.write_json(args.out, doc)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
