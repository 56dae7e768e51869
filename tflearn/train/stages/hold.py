"""Stage ``hold`` (``solver.hold.enabled``; method pipeline, last) — the learned programs
held on their paths. On a basis of a few fields a motion's program is the one that gives
its torques, and it is soft (a field weighted w gives the stiffness w K, small while its
step rises) and undamped: a push carries the limb away. Antagonist pairs
(:func:`tflearn.fit.layout.spanning_basis`, ``solver.hold``'s layout) join the learned
fields, every field damped by ``solver.hold.damping``; every motion's weights on all the
fields are solved again by one NNLS on its torques and a stiffness about its path
(:func:`tflearn.fit.impedance.solve_weights`: opposing fields whose torques cancel on the
path co-contract). The torque the held weights leave unmatched moves the limb off its
path by about that torque over the stiffness; which settings keep it within the bars
depends on the motion, so each motion takes the first of ``solver.hold.settings()``
(deviations δ, the stiffest first, each with fewer and then more sub-movement windows a
second) whose program one simulation finds reproducing it. The held model becomes the
run's result when every motion the learned one reproduced is still reproduced. One unit,
one iteration.
"""
from __future__ import annotations

import math

import torch

from ... import synthesis
from ...fit import layout
from ...fit.targets import Targets, submovement_windows
from ...model.fields import FieldBasis
from ...model.program import model_state
from ..context import RunContext
from ..models import final_model
from ..state import HoldRecord, RunState

NAME, TITLE, UNIT = "hold", "hold the programs on their paths: antagonist pairs", "stage"

__all__ = ["run", "held_model", "held_programs"]


def run(ctx: RunContext, state: RunState) -> None:
    """The held model (:func:`held_model`, :func:`held_programs`), kept when it reproduces
    every motion the run's result did (module docstring). One checkpoint."""
    tg, h = ctx.tg, ctx.cfg.solver.hold
    ctx.log.stage(NAME, 1)
    basis, weights = final_model(state)
    _, before = ctx.check(basis, weights, tg)
    grown, held = held_model(ctx.body, tg, basis, weights, h)
    chosen, ok, failures = held_programs(ctx, grown, held, h.settings())
    lost = [tg.names[j] for j, (b, a) in enumerate(zip(before, ok)) if b and not a]
    if lost:
        ctx.log.message(_refusal(lost, [failures[tg.names.index(n)] for n in lost]))
    if not lost:
        state.model = model_state(grown, held)
        if state.path is not None:
            state.path.best = None
    state.history.hold = HoldRecord(
        added=grown.M - basis.M, M=basis.M if lost else grown.M, lost=lost, kept=not lost,
        settings={n: None if c is None else {"window_rate": c[0], "deviation": c[1].deviation}
                  for n, c in zip(tg.names, chosen)})
    step = ctx.tick(state)
    if not lost:
        ctx.log.model(grown, held, step)
    ctx.log.status(M=state.history.hold.M, reproduced=f"{sum(ok)}/{tg.N}", kept=not lost)
    ctx.log.end_stage()
    state.advance(ctx.sequence)
    ctx.save(state)


def _refusal(lost: list, failures: list) -> str:
    """Why the held model is not kept, naming the motions it would lose."""
    failed = [f"{n} ({f})" for n, f in zip(lost, failures) if f is not None]
    return (f"hold: the learned model kept; held, {len(lost)} motion(s) would be lost: {', '.join(lost)}"
            + (f"; simulations failed: {', '.join(failed)} (held programs take more steps: raise "
               f"solver.path.max_evals, e.g. to 100000)" if failed else ""))


def held_model(body, tg: Targets, basis: FieldBasis, weights, h) -> tuple:
    """(grown basis, weights before their solve): ``basis``' fields followed by the layout
    of ``h`` (:class:`tflearn.config.HoldSection`) around the motions of ``tg``, every field
    damped by ``h.damping`` (the layout's kind, diagonal where ``basis``' is scalar and
    the layout's pairs; the joint simplices' blocks); ``weights`` with
    zero weights on the new fields and room for the most windows a setting asks,
    P = ⌈max(``h.window_rates``) × the longest duration⌉, all zero, cut at the first rate."""
    kind = "diag" if basis.kind == "scalar" else basis.kind
    template = FieldBasis.empty(body.nv, kind, body.blocks, h.damping)
    laid = layout.spanning_basis(body, tg, template, h.radius, h.stiffness, h.shape, h.fields)
    grown = laid.like(torch.cat([basis.eta.detach(), laid.eta]), torch.cat([basis.K().detach(), laid.K()]))
    P = math.ceil(max(h.window_rates) * float(tg.duration.max()))
    windows = submovement_windows(tg, P, rate=h.window_rates[0])
    return grown, weights.extend_fields(laid.M).with_windows(*windows)


def held_programs(ctx: RunContext, basis: FieldBasis, weights, settings: list) -> tuple:
    """Each motion's held program on ``basis``, in ``weights`` (in place):
    :func:`tflearn.synthesis.held_ladder` over ``settings`` with ``solver.ridge``, each
    setting's programs judged by the run's simulation and bars (:meth:`RunContext.check`)."""
    def judge(sub, part):
        scores, now = ctx.check(basis, sub, part)
        return scores.failure, now
    return synthesis.held_ladder(ctx.body, basis, weights, ctx.tg, settings, judge, ctx.cfg.solver.ridge)
