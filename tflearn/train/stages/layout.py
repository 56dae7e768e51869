"""Stage ``layout`` (``solver.method: layout``, in place of ``each``, ``pool`` and
``reduce``) — the spanning fields of :func:`tflearn.fit.layout.spanning_basis` around all
the motions (``solver.layout``), every motion's weights on its ``model.windows``
sub-movement windows by NNLS (``solver.ridge``; with ``solver.layout.frequency`` the
stiffness about the path asked too, :mod:`tflearn.fit.impedance`), the model scored by
simulation; path matching follows. One unit, one iteration.
"""
from __future__ import annotations

from ...fit import impedance
from ...model.program import model_state
from ..context import RunContext
from ..models import layout_model
from ..state import ModelRecord, RunState

NAME, TITLE, UNIT = "layout", "lay out spanning fields", "stage"


def run(ctx: RunContext, state: RunState) -> None:
    """The laid-out model, its weights, its scores; one checkpoint."""
    tg = ctx.tg
    ctx.log.stage(NAME, 1)
    basis, weights = layout_model(ctx.cfg, ctx.body, tg)
    c = ctx.cfg.solver
    costs = impedance.solve_weights(ctx.body, basis, weights, tg, c.layout.impedance(), ridge=c.ridge)
    cost = float(costs.sum())
    scores, ok = ctx.check(basis, weights, tg)
    step = ctx.tick(state)
    ctx.log.scalar("torque_cost/layout", cost, step)
    ctx.log.scores(scores, tg, step, figures=True)
    ctx.log.model(basis, weights, step)
    state.model = model_state(basis, weights)
    state.history.layout = ModelRecord(M=basis.M, torque_cost=cost, success=ok)
    ctx.log.status(M=basis.M, cost=cost, reproduced=f"{sum(ok)}/{tg.N}")
    ctx.log.end_stage()
    state.advance(ctx.sequence)
    ctx.save(state)
