"""Path matching by simulation (thesis §4.5.1).

All N motions are simulated together (:func:`~.targets.simulate_targets`) from their own
initial states under their own torque programs. With e_t = q_sim ⊖ q_target
(:func:`tflearn.physics.configspace.difference`), the path loss of motion j is

    L_j = Σ_t w_t (‖e_t‖² + β ‖v_sim,t − v_target,t‖²) / λ_j

and :func:`path_step` takes one safeguarded Adam step on Σ_j L_j. A step whose
simulation fails, or whose loss or gradient is not finite, is rejected: the parameters
go back to the best point, the learning rate halves, and a :class:`DivergenceWarning`
names the motions concerned.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Callable, Optional

import torch

from .. import parallel
from ..model.fields import FieldBasis
from ..model.program import model_from_state, model_state
from ..model.weights import MotionWeights
from ..physics.body import Body
from ..physics.configspace import difference
from ..simulation.simulate import SimOptions, SimulationFailed
from .targets import Targets, simulate_targets
from .torque import DivergenceWarning


def path_loss(body: Body, q_sim, v_sim, tg: Targets, velocity_weight: float = 0.1) -> torch.Tensor:
    """L_j (N), see the module docstring."""
    e = difference(body, tg.q, q_sim)
    r = (e ** 2).sum(-1) + velocity_weight * ((v_sim - tg.v) ** 2).sum(-1)
    return (tg.w * r).sum(-1) / tg.duration.clamp_min(1e-9)


def _params(basis, weights, fields: bool, phases: bool) -> list:
    params = [weights.a_raw, weights.b_raw, weights.c_raw]
    if fields:
        params += [basis.eta, *basis.stiffness.parameters()]
    if phases:
        params += weights.phase_parameters()
    return params


@dataclass
class PathStep:
    """What one :func:`path_step` leaves: the loss at the parameters it was given (∞ when
    rejected as non-finite), the next learning rate, the best point so far
    ({"loss", "model": :func:`~tflearn.model.program.model_state`}, None if there is none), the
    optimizer's state and, for a rejected step, why (``failure``)."""

    loss: float
    lr: float
    best: Optional[dict]
    optimizer: Optional[dict]
    failure: Optional[str] = None


def _restore(basis, weights, best: dict) -> None:
    b, w = model_from_state(best["model"])
    basis.load_state_dict(b.state_dict())
    weights.load_state_dict(w.state_dict())


def _loss(body, basis, weights, tg, velocity_weight, options, motions=None):
    """(per-motion loss (N, or of ``motions`` only: see :func:`simulate_targets`),
    failure message or None)."""
    sub = tg if motions is None else tg.select(motions)
    try:
        q_sim, v_sim = simulate_targets(body, basis, weights, sub, options, motions=motions)
    except SimulationFailed as err:
        return None, f"{err} (motions {', '.join(sub.names)})"
    losses = path_loss(body, q_sim, v_sim, sub, velocity_weight)
    bad = [n for n, x in zip(sub.names, losses.detach().tolist()) if not math.isfinite(x)]
    return losses, (f"non-finite path loss for {', '.join(bad)}" if bad else None)


def _summed_loss(body, basis, weights, tg, velocity_weight, options, shared: bool, motions=None):
    """(this process' part of Σ_j L_j over ``motions`` (indices, None: all) to
    backpropagate, the whole sum (∞ on a failure), failure message or None). Only
    ``motions`` are simulated.
    ``shared``: each rank of a run of several processes simulates its own share of them
    (:func:`tflearn.parallel.mine`); the losses and failures are gathered, so that every
    rank gets the same sum and failure."""
    if not shared:
        losses, failure = _loss(body, basis, weights, tg, velocity_weight, options, motions)
        return (None, math.inf, failure) if failure else (losses.sum(), float(losses.sum().detach()), None)
    motions = list(range(tg.N)) if motions is None else motions
    idx, losses, failure = [motions[i] for i in parallel.mine(len(motions))], None, None
    if idx:
        losses, failure = _loss(body, basis, weights, tg, velocity_weight, options, idx)
    rows = parallel.gather_motions(len(motions), [failure] * len(idx) if failure else
                                   losses.detach().tolist() if idx else [])
    failures = list(dict.fromkeys(x for x in rows if isinstance(x, str)))   # one per rank that failed
    if failures:
        return None, math.inf, "; ".join(failures)
    total = float(torch.tensor(rows, dtype=torch.float64).sum())
    return (None if losses is None else losses.sum()), total, None


def _sum_gradients(params: list) -> None:
    """Each parameter's gradient summed over the ranks of a run (zero where a rank has none)."""
    for p in params:
        p.grad = parallel.all_reduce_sum(p.grad if p.grad is not None else torch.zeros_like(p))


def path_step(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets, lr: float,
              best: Optional[dict] = None, optimizer_state: Optional[dict] = None, *,
              fields: bool = True, phases: bool = False, velocity_weight: float = 0.1,
              options: SimOptions = SimOptions(rtol=1e-6, atol=1e-8, max_evals=20000),
              motions: Optional[list] = None, distributed: bool = False) -> PathStep:
    """One safeguarded Adam step on the summed path loss Σ_j L_j.

    The loss is evaluated at the current parameters; if it is worse than the best point
    so far, or the step is rejected (see the module docstring), the parameters go back to
    the best point and the learning rate halves; otherwise the point becomes the best and
    Adam steps from it. Gradients come from backpropagation through the solver or, with
    ``options.adjoint``, the adjoint method. ``fields=False`` freezes the basis (weights
    only: held-out synthesis). ``motions``: sum over these motions only (indices; the
    others are not simulated, and their weights, with no gradient, do not move; with
    ``fields`` also held their paths stay exactly as they were). A failure at the
    starting point (no best point yet)
    leaves the parameters as they are and is returned with ``best`` None.
    ``distributed``: the ranks of a run (:mod:`tflearn.parallel`) simulate their own
    motions and sum the gradients, and every rank takes the same step."""
    params = _params(basis, weights, fields, phases)
    opt = torch.optim.Adam(params, lr=lr)
    if optimizer_state is not None:
        opt.load_state_dict(optimizer_state)
    shared = distributed and parallel.size() > 1
    local, value, failure = _summed_loss(body, basis, weights, tg, velocity_weight, options, shared,
                                         motions)
    if not failure and (best is None or value <= best["loss"]):
        best = {"loss": value, "model": model_state(basis, weights)}
        opt.zero_grad()
        if local is not None:            # None: a rank with no motions (more ranks than motions)
            local.backward()
        if shared:
            _sum_gradients(params)
        if all(bool(torch.isfinite(p.grad).all()) for p in params if p.grad is not None):
            opt.step()
            if fields:
                basis.project_()
            weights.project_()
            return PathStep(value, lr, best, opt.state_dict())
        names = tg.names if motions is None else [tg.names[j] for j in motions]
        failure = f"non-finite path-loss gradient (motions {', '.join(names)})"
    if failure:
        warnings.warn(f"path matching: step rejected: {failure}", DivergenceWarning, stacklevel=2)
    if best is not None:
        _restore(basis, weights, best)
    return PathStep(value, lr / 2, best, None, failure)


def path_match(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets,
               steps: int = 30, lr: float = 0.01, callback: Optional[Callable] = None,
               **kw) -> list:
    """``steps`` of :func:`path_step`, ending at the best point found (nothing changes if
    the simulation fails at the start). Returns the loss history; ``callback(step, loss)``
    is called after each step."""
    best, opt_state, history = None, None, []
    for step in range(steps):
        res = path_step(body, basis, weights, tg, lr, best, opt_state, **kw)
        if res.best is None:
            break
        lr, best, opt_state = res.lr, res.best, res.optimizer
        history.append(res.loss)
        if callback:
            callback(step, res.loss)
    if best is not None:
        _restore(basis, weights, best)
    return history
