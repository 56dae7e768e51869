"""Stage ``each`` — every motion alone: greedy growth of its own fields from data-driven,
seeded multi-start candidates, refined by EM (:func:`tflearn.fit.search.grow`), until
its relative torque cost C_j is below ``solver.each.tol`` and simulation reproduces it;
one whose own fields do not reproduce it has them and its weights fitted to its path by
multiple shooting (``solver.shooting.fields``).

With ``solver.each.reuse`` B, the motions come in blocks of B, and a motion first tries
the fields fitted for the blocks before its own (near-duplicates merged): its NNLS
weights over them, taken when its torque cost is within ``solver.each.reuse_tol`` and
simulation reproduces it; otherwise it is searched as above, and metrics.json says why
the library did not do (``history.each.declined``).

One unit per round — the motions from the cursor to the end of its block (without
reuse, one motion per rank) — gathered in motion order, then one checkpoint. Motion j's
own search draws from its own generator, seeded from the run's generator and j, so that
its result does not depend on which rank fits it or on the other motions.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import torch

from ... import parallel
from ...fit import search, torque
from ...fit.targets import Targets
from ...metrics import Scores
from ...model.fields import FieldBasis
from ...model.weights import MotionWeights
from ..context import RunContext
from ..models import windows
from ..state import EachRecord, FieldFit, RunState

NAME, TITLE, UNIT = "each", "each motion alone", "motions"


@dataclass
class MotionFit:
    """One motion's outcome: its ``fit`` (its fields, their timing and weights), its
    relative torque cost C_j, its number of fields M, whether simulation reproduces it,
    whether it was ``reused`` (fitted on the library's fields) or, searched, why the
    library ``declined`` it; for TensorBoard its ``scores`` and ``weights``."""

    fit: FieldFit
    cost: float
    M: int
    reproduced: bool
    reused: bool = False
    declined: Optional[str] = None
    scores: Optional[Scores] = None
    weights: Optional[MotionWeights] = None


def _own(basis: FieldBasis, weights: MotionWeights) -> FieldFit:
    """A one-motion model as the motion's fit (copied: the model may change later)."""
    return FieldFit(basis.eta.detach().clone(), basis.K().detach().clone(), weights.timing(0, weights=True))


def run(ctx: RunContext, state: RunState) -> None:
    """One round (the module docstring), then one checkpoint; past the last motion, on
    to the next stage."""
    tg, j = ctx.tg, state.cursor
    ctx.log.stage(NAME, tg.N, j)
    gen = state.generator()
    # motion k's search: seeds[k] (drawn on the CPU: the same seeds on any device)
    seeds = torch.randint(2 ** 62, (tg.N,), generator=gen, device="cpu").tolist()
    if j >= tg.N:
        state.rng = gen.get_state()
        ctx.log.end_stage()
        return state.advance(ctx.sequence)
    B = ctx.cfg.solver.each.reuse
    batch = list(range(j, min(tg.N, (j // B + 1) * B if B else j + parallel.size())))
    results = fits(ctx, library(ctx, state, tg, B * (j // B) if B else 0), tg, batch, seeds)
    state.history.each = state.history.each or EachRecord()
    for k, result in zip(batch, results):
        _record(ctx, state, k, result)
    state.cursor = batch[-1] + 1
    ctx.save(state)


def _record(ctx: RunContext, state: RunState, k: int, result: MotionFit) -> None:
    """Motion k's fit into the state and the history; one iteration, logged."""
    tg, record = ctx.tg, state.history.each
    state.fits.append(result.fit)
    record.reproduced.append(result.reproduced)
    if result.reused:
        record.reused.append(tg.names[k])
    if result.declined:
        record.declined[tg.names[k]] = result.declined
    step = ctx.tick(state)
    if result.scores is not None:
        ctx.log.scalar("torque_cost/each", result.cost, step)
        figures = ctx.cfg.log.figures is None or k < ctx.cfg.log.figures
        ctx.log.scores(result.scores, tg.select([k]), step, figures=figures, overview=False)
        ctx.log.fields(sum(len(f.eta) for f in state.fits), step, torch.cat([f.K for f in state.fits]),
                       result.weights)
    ctx.log.status(motion=tg.names[k], M=result.M, cost=result.cost, reproduced=result.reproduced,
                   reused=len(record.reused))


def library(ctx: RunContext, state: RunState, tg: Targets, upto: int) -> Optional[FieldBasis]:
    """The fields fitted for motions 0 … ``upto`` − 1, near-duplicates merged
    (:func:`~tflearn.fit.search.merge_close`), for ``solver.each.reuse``; None when
    there are none."""
    if not upto:
        return None
    own, merge = state.fits[:upto], ctx.cfg.solver.merge
    basis = ctx.template().like(torch.cat([f.eta for f in own]), torch.cat([f.K for f in own]))
    stub = MotionWeights.zeros(basis.M, tg.duration[:1])
    merged = search.merge_close(basis, stub, merge.distance, merge.stiffness)[0]
    return merged if merged.M else None


def fits(ctx: RunContext, library: Optional[FieldBasis], tg: Targets, batch: list, seeds: list) -> list:
    """The :class:`MotionFit` of motions ``batch``, in order: each on the ``library``'s
    fields where they do (:func:`reuse`), the motions shared by the ranks; then the
    declined ones' own searches (:func:`fit_one`, each told why the library did not do),
    shared by the ranks in turn, so that each rank gets as many of the costly searches
    as the others."""
    tries = [(None, None)] * len(batch) if library is None else parallel.gather_motions(
        len(batch), [reuse(ctx, library, tg, batch[i]) for i in parallel.mine(len(batch))])
    todo = [i for i, (fit, _) in enumerate(tries) if fit is None]
    own = parallel.gather_motions(len(todo), [fit_one(ctx, tg, batch[todo[i]], seeds[batch[todo[i]]])
                                              for i in parallel.mine(len(todo))])
    results = [fit for fit, _ in tries]
    for i, fit in zip(todo, own):
        results[i] = replace(fit, declined=tries[i][1])
    return results


def reuse(ctx: RunContext, library: FieldBasis, tg: Targets, k: int) -> tuple:
    """Motion k on the ``library``'s fields: its NNLS weights over them; if its relative
    torque cost is within ``solver.each.reuse_tol`` (unset: ``solver.each.tol``) and
    simulation reproduces it, (its :class:`MotionFit` on the fields it uses, None), else
    (None, why not: a line naming the cost or the simulation's errors)."""
    one, each = tg.select([k]), ctx.cfg.solver.each
    ctx.log.busy(motion=tg.names[k], reusing=library.M)
    w = MotionWeights.zeros(library.M, one.duration, one.names,
                            windows(ctx.cfg, one))
    tol = each.tol if each.reuse_tol is None else each.reuse_tol
    cost = float(torque.solve_weights(library, w, one)[0])
    used = w.used()[0].nonzero().flatten().tolist()
    if not used or not cost <= tol:
        return None, f"torque cost {cost:.3g} > {tol:g} on {len(used)} of {library.M} fields"
    basis, w = library.select(used), w.select_fields(used)
    scores, ok = ctx.check(basis, w, one, distributed=False)
    if not all(ok):
        why = scores.failure[0] or f"rmse {scores.rmse[0]:.3g} rad, tip {100 * scores.tip[0]:.3g} cm"
        return None, f"simulation on {len(used)} fields (torque cost {cost:.3g}): {why}"
    board = ctx.cfg.log.tensorboard
    return MotionFit(_own(basis, w), cost, basis.M, reproduced=True, reused=True,
                     scores=scores if board else None, weights=w if board else None), None


def fit_one(ctx: RunContext, tg: Targets, k: int, seed: int) -> MotionFit:
    """Motion k's own search (:func:`tflearn.fit.search.grow`) with a generator seeded
    ``seed``, then, if its fields do not reproduce it, :func:`shoot_alone`."""
    c = ctx.cfg.solver
    one = tg.select([k])
    ctx.log.busy(motion=tg.names[k])
    checked = {}

    def reproduced(b, w):
        checked["last"] = (b, *ctx.check(b, w, one, distributed=False))
        return all(checked["last"][2])
    options = search.GrowOptions(max_fields=c.each.max_fields, tol=c.each.tol,
                                 candidates=c.init.candidates, stiffnesses=tuple(c.init.stiffness_grid),
                                 em_steps=c.em.steps, em_tol=c.em.tol, phases=ctx.variable_phases)
    b, w, costs = search.grow(one, ctx.template(), torch.Generator().manual_seed(seed), options,
                              reproduced=reproduced,
                              windows=windows(ctx.cfg, one))
    if b.M and checked.get("last", (None,))[0] is not b:
        reproduced(b, w)                         # grow stopped before checking its last basis
    if b.M and not all(checked["last"][2]) and shoot_alone(ctx, b, w, one, reproduced):
        costs = torque.torque_cost(b, w, one).detach()
    last = checked.get("last")
    fresh = last is not None and last[0] is b
    board = ctx.cfg.log.tensorboard
    scores = (last[1] if fresh else ctx.check(b, w, one, distributed=False)[0]) if board else None
    return MotionFit(_own(b, w), float(costs[0]), b.M, reproduced=bool(fresh and all(last[2])),
                     scores=scores, weights=w if board else None)


def shoot_alone(ctx: RunContext, basis, weights, one: Targets, reproduced) -> bool:
    """A motion its own fields do not reproduce: those fields and its weights fitted to
    its path by multiple shooting (``solver.shooting.fields``; docs/model.md, "Programs
    whose motion is chaotic"), in place, then checked by ``reproduced``. Returns whether
    it ran."""
    if not ctx.shoot_fields(basis, weights, one):
        return False
    reproduced(basis, weights)
    return True
