"""Stage ``slsqp`` (``solver.method: slsqp``, in place of the pipeline's stages) — the
thesis' baseline (:func:`tflearn.fit.slsqp.fit_slsqp`, torque matching only) with
``model.fields`` diagonal-stiffness fields from a seeded random guess: centres at
postures drawn from the motions' samples, K = I, weights by NNLS. One unit; each SLSQP
iteration is an iteration of the run.
"""
from __future__ import annotations

import torch

from ...fit import slsqp, torque
from ...model.fields import FieldBasis
from ...model.program import model_state
from ...model.weights import MotionWeights
from ..context import RunContext
from ..state import RunState

NAME, TITLE, UNIT = "slsqp", "slsqp", "iterations"


def run(ctx: RunContext, state: RunState) -> None:
    """The random start, SLSQP to ``solver.slsqp.max_iter`` iterations, its report in
    ``history.slsqp``; one checkpoint."""
    tg, gen = ctx.tg, state.generator()
    ctx.log.stage(NAME, ctx.cfg.solver.slsqp.max_iter)
    M, n = ctx.cfg.model.fields, tg.q.shape[-1]
    flat = tg.q[tg.mask]
    eta = flat[torch.randint(len(flat), (M,), generator=gen, device="cpu")]
    basis = FieldBasis(eta, torch.eye(n, dtype=torch.float64).expand(M, n, n).clone(), kind="diag")
    weights = MotionWeights.zeros(M, tg.duration, tg.names)
    torque.solve_weights(basis, weights, tg)

    def iteration(nit, cost):
        ctx.log.scalar("torque_cost/slsqp", cost, ctx.tick(state))
        ctx.log.status(cost=cost)
    res = slsqp.fit_slsqp(basis, weights, tg, max_iter=ctx.cfg.solver.slsqp.max_iter, callback=iteration)
    ctx.log.end_stage()
    ctx.log.model(res["basis"], res["weights"], state.iteration)
    state.model = model_state(res["basis"], res["weights"])
    state.history.slsqp = {k: res[k] for k in ("initial_cost", "cost", "nit", "nfev", "message", "wall_time")}
    state.rng = gen.get_state()
    state.advance(ctx.sequence)
    ctx.save(state)
