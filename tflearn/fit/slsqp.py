"""The thesis' solver (§3.4): SQP with numerical derivatives on the torque cost.

A baseline for :func:`~.torque.em` and :func:`~.torque.joint_descent`. Every field i has
a centre η_i ∈ Rⁿ and a *diagonal* stiffness K_i = diag(k_i), k_i > 0 (the thesis'
constraint: "diagonal with positive elements, to preserve positive-definiteness, and
keep the parameter space small"); motion j has step and pulse weights a_ji, b_ji ≥ 0.
The parameter vector is

    x = [η (M×n), k (M×n), a (N×M), b (N×M)]      (row-major, 2Mn + 2NM entries)

and the cost is the same summed relative torque cost as :func:`~.torque.torque_cost`:

    C(x) = Σ_j C_j,   C_j = Σ_t w_jt ‖T_j(t) − F_j(t)‖² / S_j,   S_j = Σ_t w_jt ‖T_j(t)‖²
    F_j(t) = Σ_i (a_ji ψ_ji(t) + b_ji φ_ji(t)) χ_i(ν_j(t)),
    χ_i(ν) = −k_i ⊙ d · exp(−½ Σ_l k_il d_l²),   d = ν − η_i

(w the trapezoid weights without the trimmed end samples, ``Targets.wt``; ψ, φ the
step and pulse profiles at the motions' fixed phases). It is minimised by
``scipy.optimize.minimize(method="SLSQP")`` subject to the bounds

    a ≥ 0,   b ≥ 0,   k ≥ k_min (1e-6),   η free   (optionally k ≤ k_max, |η| ≤ eta_max),

with no gradient supplied: scipy approximates ∇C by forward differences (absolute step
``eps``, one cost evaluation per parameter per gradient), as the thesis did. SLSQP's
quasi-Newton (BFGS) model of the Hessian is built from those gradients. The cost is
evaluated in torch (float64, no autograd).

Like the thesis' runs it fails by "no motion": from a centre far from the path the field
is ≈ 0 along it, the difference gradient is ≈ 0 and SLSQP stops at once, with scipy's
``success`` set, at a cost of ≈ 1 — judge a result by its cost, not by ``success``.
"""
from __future__ import annotations

import time
from typing import Callable, Optional

import numpy as np
import torch
from scipy.optimize import minimize

from ..model.fields import FieldBasis
from ..model.weights import MotionWeights
from .targets import Targets


def pack(eta: torch.Tensor, k: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    """x = [η, diag K, a, b] flattened (row-major) as a float64 numpy vector."""
    return torch.cat([eta.reshape(-1), k.reshape(-1), a.reshape(-1), b.reshape(-1)]) \
        .detach().to(torch.float64).cpu().numpy().copy()


def unpack(x, M: int, n: int, N: int):
    """(η (M×n), k (M×n), a (N×M), b (N×M)) from a parameter vector (tensors, float64)."""
    x = torch.as_tensor(np.asarray(x, dtype=np.float64))
    sizes = [M * n, M * n, N * M, N * M]
    eta, k, a, b = torch.split(x, sizes)
    return eta.reshape(M, n), k.reshape(M, n), a.reshape(N, M), b.reshape(N, M)


def cost_function(weights: MotionWeights, tg: Targets, M: int, n: int) -> Callable:
    """C(x) → per-motion costs (N) for diagonal stiffnesses, see the module docstring.

    The motions' phases (onsets, durations) are read once from ``weights`` and held."""
    with torch.no_grad():
        psi, phi = weights.profiles_per_motion(tg.t)            # N×T×M
        psi, phi = psi.detach().clone(), phi.detach().clone()
        ws = (tg.wt / tg.torque_scale()[:, None])               # N×T
        q = tg.q.unsqueeze(-2)                                  # N×T×1×n
        tau = tg.tau
    N = tg.N

    @torch.no_grad()
    def costs(x) -> torch.Tensor:
        eta, k, a, b = unpack(x, M, n, N)
        d = q - eta                                             # N×T×M×n
        kd = k * d
        chi = -kd * torch.exp(-0.5 * (d * kd).sum(-1, keepdim=True))
        w = a[:, None, :] * psi + b[:, None, :] * phi           # N×T×M
        F = (w.unsqueeze(-1) * chi).sum(-2)                     # N×T×n
        return (ws * ((tau - F) ** 2).sum(-1)).sum(-1)
    return costs


def fit_slsqp(basis: FieldBasis, weights: MotionWeights, tg: Targets, max_iter: int = 200,
              ftol: float = 1e-12, eps: float = float(np.sqrt(np.finfo(float).eps)),
              k_min: float = 1e-6, k_max: Optional[float] = None,
              eta_max: Optional[float] = None, kind: Optional[str] = None,
              inplace: bool = False, callback: Optional[Callable] = None) -> dict:
    """Minimise Σ_j C_j over x = [η, diag K, a, b] by SLSQP with numerical derivatives.

    Starts from ``basis``' centres and the diagonal of its stiffnesses (any kind; the
    off-diagonal part is dropped) and from ``weights``' a, b (its phases are held). SLSQP
    stops after ``max_iter`` iterations or when the cost changes by less than ``ftol``
    (scipy's stopping rule); ``eps`` is the forward-difference step. The bounds are the
    thesis' (k ≥ ``k_min``, a, b ≥ 0); ``k_max`` and ``eta_max`` add k ≤ k_max and
    |η| ≤ eta_max (e.g. :data:`tflearn.model.fields.K_RANGE`, ``ETA_MAX``), off by default.

    The result is returned as a new (basis, weights) pair: FieldBasis(η, diag(k),
    kind=``kind``) — by default ``basis``' kind, except that a ``scalar`` basis gives a
    ``diag`` one (a scalar K cannot hold a general diagonal) — and MotionWeights with
    ``weights``' durations, phases and names. With ``inplace`` the given modules are also
    overwritten (not possible for a ``scalar`` basis). ``callback(nit, cost)`` is called
    after every SLSQP iteration. Returns

        {"basis", "weights", "cost" (summed, float), "costs" (per motion, list),
         "initial_cost", "nfev" (cost evaluations, finite differences included),
         "nit", "success", "status", "message", "wall_time" (s), "kind"}
    """
    M, n, N = basis.M, basis.n, weights.N
    kind = kind or ("diag" if basis.stiffness.kind == "scalar" else basis.stiffness.kind)
    if inplace and kind != basis.stiffness.kind:
        raise ValueError(f"fit_slsqp: cannot write a diagonal K into a {basis.stiffness.kind!r} basis")
    t0 = time.perf_counter()
    with torch.no_grad():
        k0 = torch.diagonal(basis.K(), dim1=-2, dim2=-1).clamp_min(k_min)
        x0 = pack(basis.eta, k0, weights.a, weights.b)
    costs = cost_function(weights, tg, M, n)
    count = [0]

    def fun(x):
        count[0] += 1
        return float(costs(x).sum())

    e_max = np.inf if eta_max is None else float(eta_max)
    lo = np.concatenate([np.full(M * n, -e_max), np.full(M * n, k_min), np.zeros(2 * N * M)])
    hi = np.concatenate([np.full(M * n, e_max), np.full(M * n, np.inf if k_max is None else k_max),
                         np.full(2 * N * M, np.inf)])
    x0 = np.clip(x0, lo, hi)
    bounds = [(None if np.isinf(l) else float(l), None if np.isinf(h) else float(h))
              for l, h in zip(lo, hi)]
    initial = fun(x0)
    cb = None
    if callback is not None:
        it = [0]

        def cb(xk):                                 # not counted in nfev: monitoring only
            it[0] += 1
            callback(it[0], float(costs(xk).sum()))

    res = minimize(fun, x0, method="SLSQP", bounds=bounds, callback=cb,
                   options={"maxiter": max_iter, "ftol": ftol, "eps": eps})
    x = np.clip(res.x, lo, hi)                      # SLSQP may step past a bound by an ulp
    eta, k, a, b = unpack(x, M, n, N)
    final = costs(x)
    with torch.no_grad():
        nb = FieldBasis(eta, torch.diag_embed(k), kind=kind, blocks=basis.blocks)
        nw = MotionWeights(a, b, weights.duration, weights.step_onset.detach(),
                           weights.step_duration.detach(), weights.pulse_onset.detach(),
                           weights.pulse_duration.detach(), names=weights.names)
        if inplace:
            basis.load_state_dict(nb.state_dict())
            weights.load_state_dict(nw.state_dict())
    return {"basis": nb, "weights": nw, "cost": float(final.sum()), "costs": final.tolist(),
            "initial_cost": initial, "nfev": count[0], "nit": int(res.nit),
            "success": bool(res.success), "status": int(res.status), "message": str(res.message),
            "wall_time": time.perf_counter() - t0, "kind": kind}
