"""Stage ``reduce`` — backward elimination: drop each field in turn, smallest share
first (:func:`~tflearn.fit.search.field_shares`), and keep it dropped if no motion gets
worse by simulation (:func:`no_worse`); the smallest M found is reported. One unit per
field tried.

With ``model.fields`` = 0 a field goes only if no motion gets worse; a field no motion
uses goes as it is (:func:`idle`), and a field that a motion not reproduced needs is kept
without a trial (:func:`carried`) — where the motion's own fit reproduced it: a motion
no fit of its own reproduces holds no field (``Reference.required``). Any other is
tried first with every field refitted by EM (:func:`refit_trial`;
``solver.reduce.refit``), then, if that breaks a motion or refitting is off, with
every other field held where it is (:func:`held_trial`: only the
motions that used it re-solve their weights and are simulated again, and the few it
loses are path-matched on the smaller basis, ``solver.reduce.shoot``). With ``sharing:
own`` a motion that loses one of its fields may then use every field left (or those in
reach, ``solver.reduce.reach``). A field the held trial may not remove, and that
nearly coincides with a field left, is tried once more folded into it
(:func:`folded_trial`: that field fitted to the paths of the motions the removal lost
and of its most sensitive users, all at once; ``solver.reduce.fold``). With
``model.fields`` = M the smallest-share fields go until M remain (refitted).

With ``solver.path.batch: each`` (one process) the refitted trials of the next fields
are checked together in one simulation (:func:`~tflearn.metrics.score_models`) and
applied in order up to the first removal, the rest dropped: the same decisions as one
at a time, since each motion's simulation is then independent of its batch; the window
(``state.window``) doubles after trials that all keep their field, and starts again at
one after a removal.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional

import torch

from ... import parallel
from ...fit import search, select, torque
from ...fit.targets import Targets
from ...metrics import Scores, score_models
from ...model.program import model_from_state, model_state
from ..context import RunContext
from ..models import weight_support
from ..state import Reference, Removal, RunState

NAME, TITLE, UNIT = "reduce", "reduce: try dropping fields", "fields"


@dataclass
class Trial:
    """A field tried for removal: its id (``victim``), how (``kind``: ``refit``,
    ``held``, ``folded`` into a near copy, or ``none``: kept without a trial,
    ``refused`` saying why), the positions
    kept, the model without it (basis, weights) and the fields each motion may then use
    (``support``), its summed torque cost Σ_j C_j (``costs``: per motion, for a held
    trial, and for a refitted one once judged where a motion was not reproduced), its EM
    steps, and its check — (scores, success) of the ``motions`` simulated
    — with, once judged under ``solver.reduce.growth``, their e-folds of error growth."""

    victim: int
    kind: str
    model: Optional[tuple] = None
    keep: Optional[list] = None
    support: Optional[list] = None
    cost: Optional[float] = None
    costs: Optional[list] = None
    em_steps: int = 0
    check: Optional[tuple] = None
    motions: list = field(default_factory=list)
    refused: Optional[str] = None
    efolds: Optional[list] = None


def no_worse(reference: Reference, scores: Scores, ok: list, costs: Optional[list] = None,
             tol: float = 0.0) -> bool:
    """Whether a smaller basis keeps every motion as good as ``reference``: a motion
    reproduced stays reproduced; one not reproduced is still simulated and has joint RMSE
    and tip error no larger than before (a failed simulation is never "no worse",
    whatever the reference: ∞ ≤ ∞ does not count), or its relative torque cost C_j
    (``costs``, where given) rose by at most ``tol`` (δ): the fields such a motion needs
    are kept (:func:`carried`), and its simulation, already off its path, cannot tell
    what losing another costs it. Over k removals its C_j may so rise by k·δ at most.
    A motion not reproduced that is not ``reference.required`` (no fit of its own
    reproduced it) may get worse: it keeps no field."""
    costs = costs if costs is not None and reference.cost is not None else [None] * len(ok)
    bars = reference.cost or [None] * len(ok)
    need = reference.held()

    def kept(j: int) -> bool:
        if reference.ok[j]:
            return ok[j]
        simulated = scores.failure[j] is None and scores.rmse[j] <= reference.rmse[j] and \
            scores.tip[j] <= reference.tip[j]
        return not need[j] or simulated or (costs[j] is not None and costs[j] <= bars[j] + tol)
    return all(kept(j) for j in range(len(ok)))


def run(ctx: RunContext, state: RunState) -> None:
    """The next trial (or window of trials) and its checkpoint (:func:`apply`); once M
    reaches its floor or every field was tried, on to the next stage."""
    tg, fixed = ctx.tg, ctx.cfg.model.fields
    basis, weights = model_from_state(state.model)
    if state.order is None:
        state.order = [int(i) for i in torch.argsort(search.field_shares(basis, weights, tg))]
        state.ids = list(range(basis.M))
    if state.reference.cost is None:               # kept up to date by apply
        state.reference.cost = torque.torque_costs(basis, weights, tg).tolist()
    k, floor = state.cursor, max(fixed, 1)

    def total(M):                        # fields to try: at most one per field, until M = floor
        return min(len(state.order), k + max(M - floor, 0))
    ctx.log.stage(NAME, total(basis.M), k)
    if basis.M <= floor or k >= len(state.order):
        ctx.log.end_stage()
        return state.advance(ctx.sequence)
    refit = fixed or ctx.cfg.solver.reduce.refit
    together = refit and not fixed and ctx.options.batch == "each" and parallel.size() == 1
    window = state.window if together else 1
    victims = state.order[k:total(basis.M)][:window]
    carried_ = set() if fixed else carried(ctx, basis, weights, state)
    idle_ = set() if fixed else idle(weights, state)
    if victims[0] in carried_:                     # kept without a trial
        apply(ctx, state, Trial(victims[0], "none", refused="needed by a motion not reproduced"), tg, total)
        return
    if victims[0] in idle_:                        # removed as it is: nothing changes
        apply(ctx, state, held_trial(ctx, basis, weights, tg, state, victims[0]), tg, total)
        return
    victims = victims[:next((i for i, v in enumerate(victims) if v in carried_ | idle_), len(victims))]
    trials = [refit_trial(ctx, basis, weights, tg, state, v) for v in victims] if refit else []
    if trials and not fixed:
        for trial, check in zip(trials, checks(ctx, [t.model for t in trials], tg)):
            trial.check = check
    for i, victim in enumerate(victims):           # each field: refitted, else held
        trial = trials[i] if refit else None
        if not (refit and accepts(ctx, state, trial, tg)) and not fixed:
            held = held_trial(ctx, basis, weights, tg, state, victim)
            trial = held if accepts(ctx, state, held, tg) or not refit else trial
            if not accepts(ctx, state, trial, tg):
                trial = folded_trial(ctx, basis, weights, tg, state, held) or trial
        removed = accepts(ctx, state, trial, tg)
        state.window = 1 if removed else 2 * window if i == len(victims) - 1 else window
        if apply(ctx, state, trial, tg, total):
            return


def carried(ctx: RunContext, basis, weights, state: RunState) -> set:
    """The fields (ids) that a motion not reproduced, but simulated to its end, needs:
    of the fields it has a weight on, the fewest whose torque cost stays within
    ``solver.select.tol`` of its cost on all of them (:func:`~tflearn.fit.select.needed`).
    Elimination keeps them: such a motion's path is still to be matched (multiple
    shooting, the path stage), which needs its fields, and its simulation, already off
    the path, cannot show what losing one costs (a removal judged by it left
    straight_reach with two fields that shooting could not carry). The others it draws
    on (copies of a needed field, fields its weights touch without need) are tried like
    any field, as are the fields of a motion whose simulation fails: a removal that lets
    it be simulated is one that path matching needs. A motion that is not
    ``reference.required`` carries none."""
    ref, used, tol = state.reference, weights.used(), ctx.cfg.solver.select.tol
    keep, need = set(), ref.held()
    for j, (ok, r, n) in enumerate(zip(ref.ok, ref.rmse, need)):
        if n and not ok and math.isfinite(r):
            keep.update(select.needed(basis, weights, ctx.tg, j, used[j].nonzero().flatten().tolist(), tol))
    return {state.ids[i] for i in keep}


def idle(weights, state: RunState) -> set:
    """The fields (ids) on which no motion has a weight: removed without a refit (its
    held trial changes no motion's torques, so it needs no simulation either)."""
    return {state.ids[i] for i in (~weights.used().any(0)).nonzero().flatten().tolist()}


def without(ctx: RunContext, basis, weights, state: RunState, victim: int, tg: Targets) -> tuple:
    """(its position, the positions kept, basis, weights, support) once field
    ``victim`` is gone; a motion that lost it may use any field left, or with
    ``solver.reduce.reach`` its own and those in reach (:func:`reach`)."""
    pos = state.ids.index(victim)
    keep = [i for i in range(basis.M) if i != pos]
    nb = basis.select(keep)
    support = None if state.support is None else [[row[i] for i in keep] for row in state.support]
    for j, row in enumerate(state.support or []):
        if row[pos]:
            support[j] = reach(ctx, nb, tg, j, support[j])
    return pos, keep, nb, weights.select_fields(keep), support


def reach(ctx: RunContext, basis, tg: Targets, j: int, own: list) -> list:
    """The fields motion j may draw on once it has lost one: every field of ``basis``,
    or with ``solver.reduce.reach`` r > 0 its ``own`` (bools) and those whose Gaussian
    exp(−½ dᵀKd) reaches r at one of its samples at least."""
    r = ctx.cfg.solver.reduce.reach
    if not r:
        return [True] * basis.M
    near = (basis.gaussians(tg.q[j][tg.mask[j]]) >= r).any(0).tolist()
    return [a or b for a, b in zip(own, near)]


def refit_trial(ctx: RunContext, basis, weights, tg: Targets, state: RunState, victim: int) -> Trial:
    """The basis without field ``victim``, refitted by EM (its EM steps counted, to be
    iterations of the run when the trial is applied); not yet checked."""
    _, keep, nb, nw, support = without(ctx, basis, weights, state, victim, tg)
    ctx.log.busy(M=basis.M, trying=victim)
    history = ctx.em(nb, nw, tg, support=support)
    return Trial(victim, "refit", model=(nb, nw), keep=keep, support=support, cost=history[-1],
                 em_steps=len(history) - 1, motions=list(range(tg.N)))


def held_trial(ctx: RunContext, basis, weights, tg: Targets, state: RunState, victim: int) -> Trial:
    """The basis without field ``victim``, every other field held: the motions with a
    weight on it (a, b or c) get their weights re-solved by NNLS over the fields left
    and are checked by simulation (:func:`held_check`, which may path-match a few of
    them); the others keep their weights, paths and scores."""
    pos, keep, nb, nw, support = without(ctx, basis, weights, state, victim, tg)
    users = weights.used()[:, pos].nonzero().flatten().tolist()
    ctx.log.busy(M=basis.M, holding=victim, motions=len(users))
    check, costs = None, state.reference.cost
    if users:
        sub, one = nw.select_motions(users), tg.select(users)
        after = torque.solve_weights(nb, sub, one, None if support is None else
                                     weight_support([support[j] for j in users], nw.P))
        keys = ("a_raw", "b_raw", "c_raw")
        nw.set_flat(keys, sub.flat(keys), users)
        costs = costs.copy()
        for j, x in zip(users, after.tolist()):
            costs[j] = x
        users, check, shot = held_check(ctx, state, users, (nb, nw), costs)
        _costed(costs, nb, nw, tg, shot)           # their weights moved off the NNLS optimum
    return Trial(victim, "held", model=(nb, nw), keep=keep, support=support, cost=math.fsum(costs),
                 costs=costs, check=check, motions=users)


def folded_trial(ctx: RunContext, basis, weights, tg: Targets, state: RunState,
                 held: Trial) -> Optional[Trial]:
    """Field ``held.victim`` folded into its twin, the nearest field left that nearly
    coincides with it (:func:`~tflearn.fit.search.coincide` by ``solver.merge``'s
    distance and stiffness: a copy of one field that motions found apart): the twin is
    fitted by multiple shooting, free, to the paths of the reproduced motions that the
    held trial lost and of up to ``solver.select.users`` reproduced users of the twin
    whose simulations amplify errors most (e-folds of growth), all at once
    (:meth:`RunContext.fit_shared`); then every user of the victim or of the twin is
    simulated (:func:`held_check`). None where ``solver.reduce.fold`` or the shooting of
    fields is off, there is no twin or nothing was lost; ``refused``, naming the motions,
    where the fit leaves a lost motion unreproduced or the moved twin loses a user."""
    c, ref = ctx.cfg.solver, state.reference
    lost = [j for j, o in zip(held.motions, held.check[1] if held.check else []) if ref.ok[j] and not o]
    pos = state.ids.index(held.victim)
    twin = _twin(basis, pos, c.merge.distance, c.merge.stiffness)
    if not (c.reduce.fold and c.shooting.fields and c.shooting.iterations and lost and twin is not None):
        return None
    (nb, nw), t = held.model, held.keep.index(twin)
    used = nw.used()
    users = [j for j in used[:, t].nonzero().flatten().tolist() if ref.ok[j] and j not in lost]
    growth = torch.tensor(ctx.efolds(nb, nw.select_motions(users), tg.select(users)) if users else [])
    motions = lost + [users[i] for i in torch.argsort(growth, descending=True, stable=True)[:c.select.users]]
    ctx.log.busy(M=basis.M, folding=held.victim, into=state.ids[twin], lost=len(lost))
    drives = [sorted({*used[j].nonzero().flatten().tolist(), t}) for j in motions]
    fit, into = ctx.fit_shared(nb, nw, motions, drives, [t]), f"folded into field {state.ids[twin]}"
    if not all(fit[2][:len(lost)]):
        left = [tg.names[j] for j, f in zip(lost, fit[2]) if not f]
        return Trial(held.victim, "folded", refused=f"{into}: fitted to {len(motions)} paths, it leaves "
                                                    f"{', '.join(left)} unreproduced")
    fb, fw, _ = fit
    support = None if held.support is None else [list(row) for row in held.support]
    for j in motions if support is not None else ():
        support[j][t] = True
    changed = sorted({*weights.used()[:, pos].nonzero().flatten().tolist(),
                      *fw.used()[:, t].nonzero().flatten().tolist(), *motions})
    costs = _costed(list(held.costs), fb, fw, tg, changed)
    done, check, shot = held_check(ctx, state, changed, (fb, fw), costs)
    _costed(costs, fb, fw, tg, shot)
    after = [tg.names[j] for j, f in zip(done, check[1]) if ref.ok[j] and not f]
    return Trial(held.victim, "folded", model=(fb, fw), keep=held.keep, support=support,
                 cost=math.fsum(costs), costs=costs, check=check, motions=done,
                 refused=f"{into}: {', '.join(after)} no longer reproduced" if after else None)


def _costed(costs: list, basis, weights, tg: Targets, motions: list) -> list:
    """``costs`` (every motion's), those of ``motions`` replaced in place by their torque
    costs on the model (basis, weights of every motion)."""
    if motions:
        for j, x in zip(motions, torque.torque_costs(basis, weights.select_motions(motions),
                                                     tg.select(motions)).tolist()):
            costs[j] = x
    return costs


def _twin(basis, pos: int, distance: float, stiffness: float) -> Optional[int]:
    """The position of the field nearest field ``pos`` (centres, rad) among those that
    nearly coincide with it (:func:`~tflearn.fit.search.coincide`); None if none does."""
    near = search.coincide(basis, distance, stiffness)[pos]
    near[pos] = False
    if not near.any():
        return None
    d = (basis.eta.detach() - basis.eta.detach()[pos]).norm(dim=1)
    return int(torch.where(near, d, torch.full_like(d, math.inf)).argmin())


def held_check(ctx: RunContext, state: RunState, users: list, new: tuple, costs: list) -> tuple:
    """(the motions simulated, their (scores, success), those path-matched) for a held
    trial of ``users``: ``new`` (basis, weights of every motion) the model without the
    field, ``costs`` every motion's torque cost on it. All
    users in one check, or with ``solver.reduce.chunk`` c > 0, c at a time, those whose
    torque cost rose most first, until a chunk holds a motion worse than its reference:
    the trial is then refused, as it would be had every user been simulated. Reproduced
    motions that a check loses, up to ``solver.reduce.shoot`` in all, are first
    path-matched on the smaller basis (:meth:`RunContext.path_matched`, their weights
    in ``new`` changed in place)."""
    c, (basis, weights), ref = ctx.cfg.solver.reduce.chunk, new, state.reference
    limit, tol = ctx.cfg.solver.reduce.shoot, ctx.cfg.solver.select.tol
    order = list(range(len(users)))
    if c:
        rise = (torch.tensor([costs[j] for j in users], dtype=torch.float64)
                / torch.tensor([ref.cost[j] for j in users], dtype=torch.float64).clamp_min(1e-300))
        order = torch.argsort(rise, descending=True, stable=True).tolist()
    done, parts, shot = [], [], []
    step = c or len(order)
    for lo in range(0, len(order), step):
        part = [users[i] for i in order[lo:lo + step]]
        scores, ok = ctx.check(basis, weights.select_motions(part), ctx.tg.select(part),
                               until_failure=not limit)
        lost = [j for j, o in zip(part, ok) if ref.ok[j] and not o]
        if lost and len(shot) + len(lost) <= limit:
            matched, fine = ctx.path_matched(basis, weights, lost)
            scores, ok = scores.replaced([part.index(j) for j in lost], matched), list(ok)
            shot += lost
            for j, f in zip(lost, fine):
                ok[part.index(j)] = f
        done, parts = done + part, parts + [scores]
        if not no_worse(ref.select(part), scores, ok, [costs[j] for j in part], tol):
            break
    scores = Scores.join(parts)
    return done, (scores, scores.succeeded(ctx.cfg.success.rmse, ctx.cfg.success.tip)), shot


def checks(ctx: RunContext, models: list, tg: Targets) -> list:
    """(scores, success) of each model, for a trial's judge (:func:`accepts`, which
    refuses any failed simulation): one batch for several, else the run's check up to
    the first failure."""
    if len(models) == 1:
        return [ctx.check(*models[0], tg, until_failure=True)]
    return [(s, s.succeeded(ctx.cfg.success.rmse, ctx.cfg.success.tip))
            for s in score_models(ctx.body, models, tg, ctx.options)]


def accepts(ctx: RunContext, state: RunState, trial: Trial, tg: Targets) -> bool:
    """Whether a trial's check keeps every motion it simulated (``trial.motions``) no
    worse than the reference and, with ``solver.reduce.growth``, adds no more than that
    many e-folds of error growth to any of them (``trial.efolds``, computed once); a
    ``refused`` trial is not accepted; one without a check (a fixed M, or a field no
    motion used) is."""
    if trial.refused:
        return False
    if trial.check is None:
        return True
    ref = state.reference.select(trial.motions)
    if trial.costs is None and not all(ref.ok):       # a refitted trial: every motion's costs moved
        trial.costs = torque.torque_costs(*trial.model, tg).tolist()    # once, for _adopt too
    costs = None if trial.costs is None else [trial.costs[j] for j in trial.motions]
    if not no_worse(ref, *trial.check, costs, ctx.cfg.solver.select.tol):
        return False
    allow = ctx.cfg.solver.reduce.growth
    if allow is None:
        return True
    if trial.efolds is None:
        nb, nw = trial.model
        trial.efolds = ctx.efolds(nb, nw.select_motions(trial.motions), tg.select(trial.motions))
    ref, need = state.reference, state.reference.held()
    return all(e <= ref.efolds[j] + allow or not (need[j] or ref.ok[j])
               for j, e in zip(trial.motions, trial.efolds))


def apply(ctx: RunContext, state: RunState, trial: Trial, tg: Targets, total: Callable) -> bool:
    """Decide a trial (one iteration, after its EM steps), log it, record it and save;
    whether the field was removed."""
    state.iteration += trial.em_steps
    state.cursor += 1
    accept = accepts(ctx, state, trial, tg)
    step = ctx.tick(state)
    if trial.cost is not None:                       # a field kept without a trial has none
        ctx.log.scalar("torque_cost/reduce", trial.cost, step)
    ctx.log.scalar("reduce/removed", float(accept), step)
    if accept:
        _adopt(ctx, state, trial, tg, step)
    refused = {"refused": trial.refused} if trial.refused else {}
    ctx.log.status(total=total(len(state.ids)), M=len(state.ids), field=trial.victim, removed=accept,
                   trial=trial.kind, **(refused or {"cost": trial.cost}))
    state.history.reduce.append(Removal(trial.victim, accept, trial.kind, len(state.ids), trial.refused))
    ctx.save(state)
    return accept


def _adopt(ctx: RunContext, state: RunState, trial: Trial, tg: Targets, step: int) -> None:
    """An accepted trial's model becomes the run's; its check updates the reference of
    the motions it simulated."""
    nb, nw = trial.model
    state.model = model_state(nb, nw)
    state.ids = [state.ids[i] for i in trial.keep]
    state.support = trial.support
    ref = state.reference                 # a refitted trial changes every motion's costs
    ref.cost = trial.costs if trial.costs is not None else torque.torque_costs(nb, nw, tg).tolist()
    ctx.log.model(nb, nw, step)
    if trial.check is None:
        ctx.log.scalar("0_overview/torque_cost", trial.cost, step)
        return
    scores, ok = trial.check
    for key, x in (("rmse", scores.rmse), ("tip", scores.tip), ("ok", ok), ("efolds", trial.efolds)):
        if x is not None:
            for i, j in enumerate(trial.motions):
                getattr(ref, key)[j] = x[i]
    ctx.log.scores(scores, tg.select(trial.motions), step, overview=len(trial.motions) == tg.N)
