"""Other field representations the thesis names (§4.5.2), measured against the Gaussian
field on motions no field made: does a field with a rotational part, or one whose
stiffness grows with its activation, fit their torques better at the same number of
fields, and do its fits simulate closer?

Four field models, each driven by the same activation family (the thesis' step ψ and
pulse φ over the motion plus P pulses on overlapping windows, every weight ≥ 0) and
the same field damping ζ (as experiment 3's fields):

- ``diag``: χ(ν, v) = −K (d + ζ v) g, K = diag(k), d = ν − η, g = exp(−½ dᵀK d)
  (the library's field; irrotational for ζ = 0).
- ``full``: the same with K symmetric positive definite (21 more numbers per field of
  the arm: the irrotational control with as many parameters as ``rotational``).
- ``rotational``: χ = −(K (d + ζ v) + S d) g, K diagonal, S skew-symmetric (21 more):
  the field turns about η (curl ≠ 0) and still converges (dᵀχ = −dᵀK d · g ≤ 0 at rest).
- ``cocontraction``: each field's stiffness grows with its activation w, as
  co-contracted muscles stiffen, τ = Σ_i w_i χ_i(ν, v; K_i (1 + γ_i w_i)), γ_i ≥ 0 (one
  more number per field; γ = 0 is ``diag``).

Every model holds the fields of the library's spanning layout
(:func:`tflearn.fit.layout.spanning_basis`, M = 8: the simplex, radius 16, stiffness
1/16 of the mean inertia, the ``layout`` method's basis, whose Gaussians are ≈ 1 along
the motions) and starts from the non-negative least-squares weights on them with S = 0,
γ = 0 and the full K its diagonal (the same torques); its weights and extra numbers are
then fitted jointly by projected Levenberg–Marquardt on the pooled relative torque cost
Σ_j Σ_t w ‖τ − F‖² / Σ_j Σ_t w ‖τ‖², so what it gains over ``diag`` (the NNLS fit
itself) is what its extra freedom buys. Centres and stiffnesses are held: left free,
the fit of every model takes stiffnesses to 1e-100 along some coordinates and centres
hundreds of radians away, springs that push the same way everywhere. Each fit is simulated from every motion's
initial state (every motion its own dopri5 steps, rtol 1e-7, atol 1e-9, at most 20,000
evaluations, the training budget): joint RMSE, hand-tip error, or the failure; and its
local error growth along the target paths (:mod:`tflearn.fit.stability`), the peak rate
λ and the e-folds Λ per motion.

    PYTHONPATH=. python bench/representations.py --out runs/bench/representations.json
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import revision
import torch

F64 = torch.float64
MODELS = ("diag", "full", "rotational", "cocontraction")


def datasets(body) -> dict:
    """{name: motions}: experiment 3's six (five keyframe splines and the straight reach)
    and experiment 5's eight class reaches."""
    from tflearn.experiments.keyframes import keyframe_motions
    from tflearn.experiments.reaches import reach_class
    gestures = ["come_here", "stiff_elbow_lift", "tuck", "planar_line", "backwards_reach"]
    return {"keyframes": keyframe_motions(body, gestures), "reaches": reach_class(body)[0]}


def activations(u: torch.Tensor, pulses: int) -> torch.Tensor:
    """The activation family at motion phases u = t/T (...) → (...×(2 + P)): ψ(u), φ(u)
    and P pulses φ((u − s_p)/h) on windows of width h = 2/(P + 1) starting at s_p = p h/2."""
    from tflearn.model.weights import pulse_profile, step_profile
    h = 2.0 / (pulses + 1)
    cols = [step_profile(u), pulse_profile(u)] + [pulse_profile((u - p * h / 2) / h) for p in range(pulses)]
    return torch.stack(cols, -1)


def profiles(tg, pulses: int) -> torch.Tensor:
    """:func:`activations` on every sample of the motions (N×T×(2 + P))."""
    return activations(tg.t / tg.duration[:, None], pulses)


class Model:
    """M fields of one kind, shared, and per-motion weights c (N×M×(2+P)) ≥ 0, all in one
    parameter vector x = [θ (M×(2n+e)), c] (:meth:`unpack`), a field's θ = [η, log k,
    extra]; ``extra`` is the strictly lower triangle of L (``full``: K = L Lᵀ, L's
    diagonal √k), of S's generator A (``rotational``: S = A − Aᵀ) or γ
    (``cocontraction``)."""

    def __init__(self, kind: str, M: int, n: int, N: int, P: int, zeta: float):
        self.kind, self.M, self.n, self.N, self.P, self.zeta = kind, M, n, N, P, zeta
        self.il = torch.tril_indices(n, n, -1)
        self.e = self.il.shape[1] if kind in ("full", "rotational") else 1 if kind == "cocontraction" else 0
        self.width = 2 * n + self.e

    def pack(self, eta, k, c) -> torch.Tensor:
        theta = torch.cat([eta, k.log(), torch.zeros(self.M, self.e, dtype=F64)], -1)
        return torch.cat([theta.reshape(-1), c.reshape(-1)])

    def unpack(self, x: torch.Tensor) -> tuple:
        """(θ M×(2n+e), c N×M×P)."""
        theta, c = torch.split(x, [self.M * self.width, self.N * self.M * self.P])
        return theta.view(self.M, self.width), c.view(self.N, self.M, self.P)

    def fields(self, x: torch.Tensor) -> tuple:
        """(η M×n, k M×n, extra M×e)."""
        theta = self.unpack(x)[0]
        return theta[:, :self.n], theta[:, self.n:2 * self.n].exp(), theta[:, 2 * self.n:]

    def lower(self) -> torch.Tensor:
        """Lower bounds of x: c ≥ 0, γ ≥ 0, the rest free (−∞)."""
        lo = torch.full((self.M, self.width), -math.inf, dtype=F64)
        if self.kind == "cocontraction":
            lo[:, -1] = 0.0
        return torch.cat([lo.reshape(-1), torch.zeros(self.N * self.M * self.P, dtype=F64)])

    def _lower(self, extra: torch.Tensor) -> torch.Tensor:
        """The strictly lower triangular n×n matrix of ``extra`` (...×e)."""
        A = extra.new_zeros(*extra.shape[:-1], self.n, self.n)
        A[..., self.il[0], self.il[1]] = extra
        return A

    def field(self, theta: torch.Tensor, q: torch.Tensor, v: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """One field's torque w χ(q, v) (...×n) for its θ (2n+e), q, v (...×n) and its
        activation w (...)."""
        n = self.n
        d, k, extra = q - theta[:n], theta[n:2 * n].exp(), theta[2 * n:]
        if self.kind == "cocontraction":
            k = k * (1 + extra * w).unsqueeze(-1)
        if self.kind == "full":
            L = torch.diag(k.sqrt()) + self._lower(extra)
            K = L @ L.T
            Kd, Kv = d @ K, v @ K                                  # K symmetric
        else:
            Kd, Kv = k * d, k * v
        push = Kd + self.zeta * Kv
        if self.kind == "rotational":
            A = self._lower(extra)
            push = push + d @ (A - A.T).T
        return -w.unsqueeze(-1) * push * torch.exp(-0.5 * (d * Kd).sum(-1, keepdim=True))

    def torques(self, x: torch.Tensor, q: torch.Tensor, v: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """τ (...×n) for q, v (...×n) and every field's activation w (...×M)."""
        theta = self.unpack(x)[0]
        return sum(self.field(theta[i], q, v, w[..., i]) for i in range(self.M))

    def weights(self, x: torch.Tensor, prof: torch.Tensor) -> torch.Tensor:
        """w_ij(t) (N×T×M) = Σ_p c_ijp profile_p(t)."""
        return torch.einsum("ntp,nmp->ntm", prof, self.unpack(x)[1])

    def jacobian(self, x: torch.Tensor, tg, prof) -> torch.Tensor:
        """d residual / dx (R × X), by blocks: each field's θ by forward mode on that field
        alone, each weight c_ijp as profile_p · ∂(w χ_i)/∂w on motion j's rows."""
        theta, _ = self.unpack(x)
        w = self.weights(x, prof)
        N, T, n, M, P = self.N, tg.t.shape[1], self.n, self.M, self.P
        s = -(tg.wt.sqrt() / scale(tg)).unsqueeze(-1)                         # N×T×1
        J = torch.zeros(N, T, n, M * self.width + N * M * P, dtype=F64)
        cw = J[..., M * self.width:].view(N, T, n, N, M, P)
        for i in range(M):
            th, wi = theta[i], w[..., i]
            Jt = torch.func.jacfwd(lambda t, wi=wi: self.field(t, tg.q, tg.v, wi))(th)
            J[..., i * self.width:(i + 1) * self.width] = s.unsqueeze(-1) * Jt
            _, g = torch.func.jvp(lambda a, th=th: self.field(th, tg.q, tg.v, a), (wi,),
                                  (torch.ones_like(wi),))
            for j in range(N):
                cw[j, :, :, j, i, :] = (s[j] * g[j]).unsqueeze(-1) * prof[j].unsqueeze(1)
        return J.reshape(N * T * n, -1)


def scale(tg) -> torch.Tensor:
    """√(Σ_j Σ_t w ‖τ‖²): the pooled torque norm."""
    return (tg.wt * (tg.tau ** 2).sum(-1)).sum().sqrt()


def residual(model: Model, x: torch.Tensor, tg, prof) -> torch.Tensor:
    """√(w_t) (τ − F) / √(Σ w ‖τ‖²), flattened: its square sum is the relative torque cost."""
    F = model.torques(x, tg.q, tg.v, model.weights(x, prof))
    return (tg.wt.sqrt().unsqueeze(-1) * (tg.tau - F) / scale(tg)).reshape(-1)


def start(body, tg, prof, zeta: float) -> tuple:
    """The spanning layout's fields (η M×n, k M×n) and the NNLS weights on them
    (N×M×(2+P)): every model's start."""
    from scipy.optimize import nnls

    from tflearn.config import Layout
    from tflearn.fit.layout import spanning_basis
    from tflearn.model.fields import FieldBasis
    lay = Layout()                                     # the layout method's defaults
    basis = spanning_basis(body, tg, FieldBasis.empty(body.nv, "diag"), lay.radius, lay.stiffness,
                           lay.shape)
    eta, k = basis.eta.detach(), torch.diagonal(basis.K().detach(), dim1=-2, dim2=-1)
    model = Model("diag", len(eta), body.nv, tg.N, prof.shape[-1], zeta)
    x = model.pack(eta, k, torch.zeros(tg.N, len(eta), prof.shape[-1], dtype=F64))
    r0 = residual(model, x, tg, prof)
    A = -model.jacobian(x, tg, prof)[:, -tg.N * model.M * model.P:]
    c = nnls(A.numpy(), r0.numpy(), maxiter=20 * A.shape[1])[0]
    return eta, k, torch.as_tensor(c).view(tg.N, model.M, model.P)


def fit(model: Model, x: torch.Tensor, tg, prof, steps: int):
    """Projected Levenberg–Marquardt on the residual, every field's η and k held
    (Marquardt's diagonal scaling; a bounded variable at its bound whose gradient pushes
    it out is held there for the step); (x, the relative torque cost at the start and
    the end, the steps taken)."""
    lo = model.lower()
    held = torch.zeros_like(x, dtype=torch.bool)
    held[:model.M * model.width].view(model.M, model.width)[:, :2 * model.n] = True
    r = residual(model, x, tg, prof)
    cost0 = cost = float(r @ r)
    mu, taken = 1e-3, 0
    for _ in range(steps):
        J = model.jacobian(x, tg, prof)
        g = J.T @ r
        free = ((x > lo) | (g < 0)) & ~held
        A = (J.T @ J)[free][:, free]
        D = A.diagonal().clamp_min(1e-12)
        while mu < 1e12:
            step = torch.zeros_like(x)
            step[free] = -torch.linalg.solve(A + mu * torch.diag(D), g[free])
            y = torch.maximum(x + step, lo)
            ry = residual(model, y, tg, prof)
            if float(ry @ ry) < cost:
                break
            mu *= 10
        else:
            break
        gain = cost - float(ry @ ry)
        x, r, cost, mu, taken = y, ry, float(ry @ ry), max(mu / 10, 1e-9), taken + 1
        if gain < 1e-10 * cost:
            break
    return x, cost0, cost, taken


def program_of(model: Model, x: torch.Tensor, tg, pulses: int):
    """The fitted program, τ(t, ν, v) with t each motion's own time (...×N)."""
    c = model.unpack(x)[1]

    def program(t, q, v):
        w = torch.einsum("...np,nmp->...nm", activations(t / tg.duration, pulses), c)
        return model.torques(x, q, v, w)
    return program


def growth(body, program, tg) -> dict:
    """Per motion, the local error growth rate's peak λ (1/s) and e-folds Λ along the
    target path (:mod:`tflearn.fit.stability`: the closed loop linearised about it)."""
    from tflearn.fit.stability import program_growth
    g = program_growth(body, program, tg)
    return {n: {"peak_per_s": float(a), "efolds": float(b)} for n, a, b in zip(tg.names, g.peak, g.efolds)}


def simulate(body, program, tg) -> dict:
    """Every motion simulated from its initial state under ``program``."""
    from tflearn.metrics import path_errors
    from tflearn.simulation.simulate import SimOptions
    from tflearn.simulation.simulate import simulate as sim
    out = {}
    with torch.no_grad():
        traj = sim(body, program, tg.q0, tg.qd0, tg.grid,
                   SimOptions(rtol=1e-7, atol=1e-9, max_evals=20000, batch="each"), throw=False)
        q_sim = traj.q[torch.arange(tg.N)[:, None], tg.index]
        rmse, tip = path_errors(body, q_sim, tg)
    failed = traj.failure or [None] * tg.N
    for j, name in enumerate(tg.names):
        out[name] = ({"failed": str(failed[j])[:120]} if failed[j] else
                     {"rmse_rad": float(rmse[j]), "tip_cm": 100 * float(tip[j])})
    return out


def run(kind: str, body, tg, prof, fields: tuple, zeta: float, steps: int) -> dict:
    """One model fitted from ``fields`` (η, k, c) and simulated: its row."""
    model = Model(kind, len(fields[0]), body.nv, tg.N, prof.shape[-1], zeta)
    t0 = time.perf_counter()
    x, cost0, cost, taken = fit(model, model.pack(*fields), tg, prof, steps)
    _, k, extra = model.fields(x)
    c = model.unpack(x)[1]
    row = {"model": kind, "field_parameters": model.M * (2 * model.n + model.e), "cost_start": cost0,
           "cost": cost, "steps": taken, "fit_s": time.perf_counter() - t0,
           "x": x.tolist(), "largest_weight": float(c.max())}
    if kind == "rotational":
        A = model._lower(extra)
        skew = (A - A.transpose(-1, -2)).flatten(1).norm(dim=-1)
        row["skew_over_stiffness"] = (skew / k.norm(dim=-1)).tolist()
    if kind == "cocontraction":
        row["gamma_times_largest_weight"] = (extra.squeeze(-1) * c.sum(-1).amax(0)).tolist()
    program = program_of(model, x, tg, prof.shape[-1] - 2)
    row["paths"], row["growth"] = simulate(body, program, tg), growth(body, program, tg)
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sets", default="keyframes,reaches")
    p.add_argument("--models", default=",".join(MODELS))
    p.add_argument("--steps", type=int, default=200, help="Levenberg–Marquardt steps per fit, at most")
    p.add_argument("--pulses", type=int, default=4)
    p.add_argument("--zeta", type=float, default=0.2)
    p.add_argument("--out", type=Path)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    from tflearn.fit.targets import prepare
    from tflearn.physics.body import arm
    body = arm()
    sets = datasets(body)
    doc = {"commit": revision.head(), "args": {k: str(v) for k, v in vars(args).items()}, "rows": []}
    for name in args.sets.split(","):
        tg = prepare(body, sets[name])
        prof = profiles(tg, args.pulses)
        fields = start(body, tg, prof, args.zeta)
        rows = [run(kind, body, tg, prof, fields, args.zeta, args.steps) for kind in args.models.split(",")]
        for row in rows:
            paths = row["paths"]
            ok = [v for v in paths.values() if "rmse_rad" in v]
            g = row["growth"].values()
            print(f"{name:10s} {row['model']:14s} cost {row['cost_start']:.4g} -> {row['cost']:.4g} "
                  f"({row['steps']} steps, {row['fit_s']:.0f} s)  {len(paths) - len(ok)} failed, "
                  f"worst of the rest {max((v['rmse_rad'] for v in ok), default=math.nan):.3f} rad / "
                  f"{max((v['tip_cm'] for v in ok), default=math.nan):.1f} cm; growth peak "
                  f"{max(v['peak_per_s'] for v in g):.1f} /s, e-folds {max(v['efolds'] for v in g):.1f}",
                  flush=True)
            doc["rows"].append({"set": name, **row})
        revision.write_json(args.out, doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
