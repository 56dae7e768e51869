"""Path matching by simulation (thesis §4.5.1) and the reproduction metrics.

All N motions are simulated together (one batched ``odeint`` over the union of their
sample times) from their own initial states under their own torque programs. The error
of a sample is the vector e ∈ R^n with, per ball joint, the rotation from target to
simulated e = log(R_targetᵀ R_sim) (child frame; equal to ν_sim − ν_target to first order,
and well behaved where the principal rotation vector wraps at π) and, per hinge, the
angle difference. The path loss of motion j is

    L_j = Σ_t w_t (‖e_t‖² + β ‖v_sim,t − v_target,t‖²) / λ_j

and the metrics are the joint-angle RMSE sqrt(mean_t,k e²) (rad), the maximum hand-tip
distance (m) and the relative RMS torque error.
"""
from __future__ import annotations

from typing import Callable, Optional

import roma
import torch

from .. import dynamics
from ..body import Body
from ..fields import FieldBasis, FieldProgram, MotionWeights
from ..simulate import SimulationBudget, simulate
from .targets import Targets
from .torque import relative_rms_torque_error


def simulate_targets(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets,
                     method: str = "dopri5", rtol: float = 1e-7, atol: float = 1e-9,
                     adjoint: bool = False, options: Optional[dict] = None,
                     max_evals: Optional[int] = None):
    """Simulated (q, v) at every motion's samples: (N×T×n) each."""
    program = FieldProgram(basis, weights)
    tr = simulate(body, program, tg.q0, tg.qd0, tg.grid, method=method, rtol=rtol, atol=atol,
                  adjoint=adjoint, options=options, max_evals=max_evals)
    idx = tg.index.unsqueeze(-1).expand(-1, -1, body.nv)
    return tr.q.gather(1, idx), tr.v.gather(1, idx)


def coordinate_error(body: Body, q_sim: torch.Tensor, q_tgt: torch.Tensor) -> torch.Tensor:
    """e (...×n): log(R_tgtᵀ R_sim) per ball joint, θ_sim − θ_tgt per hinge."""
    parts = []
    for i, link in enumerate(body.links):
        s = body.slice(i)
        if link.joint == "ball":
            R = dynamics.rotvec_to_rotmat(q_tgt[..., s]).transpose(-1, -2) @ \
                dynamics.rotvec_to_rotmat(q_sim[..., s])
            parts.append(roma.unitquat_to_rotvec(roma.rotmat_to_unitquat(R)))
        elif link.dof:
            parts.append(q_sim[..., s] - q_tgt[..., s])
    return torch.cat(parts, dim=-1)


def path_loss(body: Body, q_sim, v_sim, tg: Targets, velocity_weight: float = 0.1) -> torch.Tensor:
    """L_j (N), see the module docstring."""
    e = coordinate_error(body, q_sim, tg.q)
    r = (e ** 2).sum(-1) + velocity_weight * ((v_sim - tg.v) ** 2).sum(-1)
    return (tg.w * r).sum(-1) / tg.duration.clamp_min(1e-9)


@torch.no_grad()
def metrics(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets,
            q_sim: Optional[torch.Tensor] = None, **sim_kw) -> dict:
    """Per-motion reproduction metrics (and the simulated path) as plain floats.

    Returns {"rmse": [N], "tip": [N], "torque": [N], "q_sim": N×T×n tensor}. A
    simulation that fails (the solver gives up, or more than ``max_evals`` evaluations)
    reproduces nothing: rmse = tip = inf, q_sim all NaN, and "error" says why. So does
    one whose state blows up until the mass matrix cannot be factorised."""
    if q_sim is None:
        try:
            q_sim, _ = simulate_targets(body, basis, weights, tg, **sim_kw)
        except (AssertionError, SimulationBudget, torch.linalg.LinAlgError) as err:
            inf = [float("inf")] * tg.N
            return {"rmse": inf, "tip": inf, "torque": relative_rms_torque_error(basis, weights, tg).tolist(),
                    "q_sim": torch.full_like(tg.q, float("nan")), "error": str(err)}
    e = coordinate_error(body, q_sim, tg.q)
    m = tg.mask.to(e.dtype)
    rmse = ((e ** 2).mean(-1) * m).sum(-1).div(m.sum(-1)).sqrt()
    tip = (dynamics.tip_position(body, q_sim) - dynamics.tip_position(body, tg.q)).norm(dim=-1)
    tip = (tip * m).amax(-1)
    torque = relative_rms_torque_error(basis, weights, tg)
    return {"rmse": rmse.tolist(), "tip": tip.tolist(), "torque": torque.tolist(), "q_sim": q_sim}


def succeeded(m: dict, rmse: float, tip: float) -> list:
    """Per motion: joint RMSE ≤ rmse and maximum tip error ≤ tip."""
    return [r <= rmse and p <= tip for r, p in zip(m["rmse"], m["tip"])]


def _params(basis, weights, fields: bool, phases: bool) -> list:
    params = [weights.a_raw, weights.b_raw]
    if fields:
        params += [basis.eta, *basis.stiffness.parameters()]
    if phases:
        params += weights.phase_parameters()
    return params


def _snapshot(basis, weights, loss) -> dict:
    return {"loss": loss, "basis": {k: v.clone() for k, v in basis.state_dict().items()},
            "weights": {k: v.clone() for k, v in weights.state_dict().items()}}


def path_step(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets, lr: float,
              best: Optional[dict] = None, optimizer_state: Optional[dict] = None,
              fields: bool = True, phases: bool = False, velocity_weight: float = 0.1,
              method: str = "dopri5", rtol: float = 1e-6, atol: float = 1e-8,
              adjoint: bool = False, max_evals: Optional[int] = 20000) -> dict:
    """One safeguarded Adam step on the summed path loss Σ_j L_j.

    The loss is evaluated at the current parameters; if it is worse than the best point
    so far (or the simulation fails: non-finite, or more than ``max_evals`` right-hand-side
    evaluations), the parameters go back to the best point and the learning rate halves;
    otherwise the point becomes the best and Adam steps from it. Gradients come from
    backpropagation through the solver or, with ``adjoint``, the adjoint method.
    ``fields=False`` freezes the basis (weights only: held-out synthesis).

    Returns {"loss", "lr", "best", "optimizer"} — everything a checkpoint needs."""
    params = _params(basis, weights, fields, phases)
    opt = torch.optim.Adam(params, lr=lr)
    if optimizer_state is not None:
        opt.load_state_dict(optimizer_state)
    try:
        q_sim, v_sim = simulate_targets(body, basis, weights, tg, method=method, rtol=rtol,
                                        atol=atol, adjoint=adjoint, max_evals=max_evals)
        loss = path_loss(body, q_sim, v_sim, tg, velocity_weight).sum()
        value = float(loss.detach())
        failed = not torch.isfinite(loss)
    except (AssertionError, SimulationBudget, torch.linalg.LinAlgError):
        failed, value = True, float("inf")
    if best is None and failed:
        raise RuntimeError("path matching: the simulation fails at the starting point")
    if best is not None and (failed or value > best["loss"]):
        basis.load_state_dict(best["basis"])
        weights.load_state_dict(best["weights"])
        return {"loss": value, "lr": lr / 2, "best": best, "optimizer": None}
    best = _snapshot(basis, weights, value)
    opt.zero_grad()
    loss.backward()
    opt.step()
    if fields:
        basis.project_()
    weights.project_()
    return {"loss": value, "lr": lr, "best": best, "optimizer": opt.state_dict()}


def path_match(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets,
               steps: int = 30, lr: float = 0.01, callback: Optional[Callable] = None,
               **kw) -> list:
    """``steps`` of :func:`path_step`, ending at the best point found. Returns the loss
    history; ``callback(step, loss)`` is called after each step."""
    best, opt_state, history = None, None, []
    for step in range(steps):
        res = path_step(body, basis, weights, tg, lr, best, opt_state, **kw)
        lr, best, opt_state = res["lr"], res["best"], res["optimizer"]
        history.append(res["loss"])
        if callback:
            callback(step, res["loss"])
    if best is not None:
        basis.load_state_dict(best["basis"])
        weights.load_state_dict(best["weights"])
    return history
