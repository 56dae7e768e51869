"""Choosing the shared basis among pooled candidate fields: a simultaneous sparse
approximation with non-negative groups, judged motion by motion.

Every motion fitted alone brings its own fields; motions made by a few shared fields
bring many copies of each, which differ along the directions their motions hardly
excite. Which copy serves a motion is a question for the motion, not for the fields'
coordinates: with the candidates fixed, motion j's relative torque cost over a subset S
of them is the non-negative least-squares optimum

    C_j(S) = min_{x ≥ 0 on the columns of S} 1 − 2 h_jᵀx + xᵀG_j x

(G_j, h_j the normal equations of :func:`~.torque.normal_equations`: each field a group
of 2 + P columns, its step, pulse and window weights). Field k *substitutes* field i for
motion j when C_j with k in place of i stays within the motion's tolerance — a distance
in the metric G_j of the directions motion j excites, so copies that differ only where
no motion looks are one field, and fields that differ where a motion looks are not.

A subset S *serves* motion j when C_j(S) ≤ τ_j = min(c_j + δ, 1 − δ), c_j the cost of
its own fit (or of its own fields' NNLS weights, where lower; at least the cost of its
fewest own fields that simulation reproduces, where given: ``floor``) and δ the tolerance
(``SelectOptions.tol``; no subset serves with no field). :func:`select` finds a small S serving
every motion (every motion its own fit reproduced, where some are: a motion no fit of
its own reproduces cannot say which fields it needs, and fields that only it draws on
are no shared fields): greedy forward selection — the candidate that removes the most excess
Σ_j max(C_j − τ_j, 0) joins, every motion's weights re-solved exactly (S-OMP's rule with
NNLS refits in place of projections, Tropp, Gilbert & Strauss 2006; each candidate a
group of columns shared by all motions, as in group-sparse NNLS) — then backward
pruning: a chosen field whose every motion is still served without it leaves. The
forward path gives each size's summed cost and count served (the knee of
:class:`Selection`). A motion sees only the candidates whose Gaussian reaches
``SelectOptions.reach`` on its path (and its own), so the cost grows with the motions,
not with their product with the candidates; the reach is relative to the motion's
weakest own field, since a field centred far from the path (its Gaussian 10⁻⁵ there,
its weights large) drives a motion as well as a near one. With many motions, candidates
in reach still grow with N (copies of each field from every motion): a screen
(``SelectOptions.block``) first lets blocks of motions choose among their own fields,
and every motion then chooses among the blocks' choices, the same screen for every
motion.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import torch

from .. import parallel
from ..model.fields import FieldBasis
from ..model.weights import MotionWeights
from .nnls import nnls
from .targets import Targets
from .torque import columns, normal_equations, quadratic_cost, solve_weights, torque_costs

__all__ = ["SelectOptions", "Selection", "needed", "reproducing_cost", "select"]


@dataclass(frozen=True)
class SelectOptions:
    """Settings of :func:`select`. tol: δ, the relative torque cost a motion may gain over
    its own fit's; reach: a candidate is one of motion j's when its Gaussian
    exp(−½ dᵀKd) reaches this at one of its samples (or it is one of its own), relative
    to the weakest of its own fields (that field's peak on the path); beyond: the
    candidates added after every motion is served, for the knee (:attr:`Selection.path`);
    block: with more motions than this, a screen first (:func:`_screen`): the motions in
    blocks of this many, each block's selection among its own motions' fields, and the
    selection over every motion among the fields some block kept (0: no screen)."""

    tol: float = 1e-4
    reach: float = 1e-4
    beyond: int = 2
    block: int = 100


@dataclass
class Selection:
    """What :func:`select` chose: ``kept``, the candidates kept (indices, in the order
    they joined); ``path``, per size m = 1, 2, … of the forward selection (first m
    candidates chosen, weights re-solved), the summed cost Σ_j C_j and the count of
    motions served ([m, cost, served]); ``pruned``, the chosen candidates pruned again;
    ``unserved``, the motions no subset serves within tolerance (their own candidates
    were out of reach of one another: never, when ``reach`` keeps their own);
    ``support``, each motion's fewest fields of ``kept`` (found greedily, by C_j) that
    serve it, or that fit it as well as all of ``kept`` can (an unserved motion);
    ``costs``, each motion's C_j on ``kept``; ``tolerance``, each motion's τ_j; ``candidates``,
    each motion's candidates (indices); ``merged``, [kept, dropped] pairs: each dropped
    candidate that was a motion's own, with the nearest kept field (Euclidean centre) that
    its motion uses instead."""

    kept: list
    path: list
    pruned: list = field(default_factory=list)
    unserved: list = field(default_factory=list)
    support: list = field(default_factory=list)
    costs: list = field(default_factory=list)
    tolerance: list = field(default_factory=list)
    candidates: list = field(default_factory=list)
    merged: list = field(default_factory=list)


class _Motion:
    """Motion j's normal equations over its candidates (``fields``, global indices, their
    groups of 2 + P columns) and its cost on the current subset."""

    def __init__(self, fields: list, G: torch.Tensor, h: torch.Tensor, P: int, tau: float):
        self.fields, self.G, self.h, self.P, self.tau = fields, G, h, P, tau
        self.local = {f: i for i, f in enumerate(fields)}
        self.cost = 1.0                                  # C_j(∅): no torque at all
        self.required = True                             # its excess counts

    def costs(self, subsets: list) -> torch.Tensor:
        """C_j of each subset (lists of global candidate indices, all the same size)."""
        return self.solve(subsets)[0]

    def solve(self, subsets: list) -> tuple:
        """(C_j of each subset (B), whether each field of a subset has a weight > 0 (B×k))."""
        if not subsets[0]:
            B = len(subsets)
            return torch.ones(B, dtype=self.G.dtype), torch.zeros(B, 0, dtype=torch.bool)
        m, k = len(self.fields), len(subsets[0])
        idx = torch.stack([columns([self.local[f] for f in s], m, self.P) for s in subsets])
        G = self.G[idx[:, :, None], idx[:, None, :]]
        h = self.h[idx]
        x = nnls(G, h).x
        cost = quadratic_cost(G, h, x)
        weight = x[:, :k] + x[:, k:2 * k] + x[:, 2 * k:].unflatten(-1, (k, self.P)).sum(-1)
        return cost, weight > 0

    def excess(self, cost: float) -> float:
        return max(cost - self.tau, 0.0) if self.required else 0.0


def _motions(basis: FieldBasis, weights: MotionWeights, tg: Targets, own: torch.Tensor,
             opts: SelectOptions, tolerance: Optional[list], among: Optional[torch.Tensor],
             required: Optional[list] = None, floor: Optional[list] = None) -> list:
    """Each motion's :class:`_Motion`: its candidates (reach, within ``among`` (M bools)
    where given, or its own, ``own`` N×M bools; of exact copies the first alone) and their
    normal equations; τ_j as given, or
    min(c_j + δ, 1 − δ), c_j its own fit's cost: on ``weights``, or the NNLS optimum on its
    own fields where that is lower (path shooting with free fields fits the path, and can
    leave weights whose torques are no motion's, C_j even above 1); at most 1 − δ, below
    C_j(∅) = 1, so that every motion needs a field; c_j at least ``floor``'s (N floats,
    :func:`select`). ``required`` (N bools; None: all): the motions whose excess counts."""
    out = []
    if tolerance is None:
        current = torque_costs(basis, weights, tg).tolist()
    mine, first = _onto_first_copies(basis, own)
    if among is not None:
        first = first & among
    for j in range(tg.N):
        peak = basis.gaussians(tg.q[j][tg.mask[j]]).max(0).values
        near = ((peak >= opts.reach * _weakest(peak, own[j])) & first) | mine[j]
        mo = _motion(basis, weights, tg, j, near.nonzero().flatten().tolist())
        if tolerance is None:
            c = min(current[j], float(mo.costs([mine[j].nonzero().flatten().tolist()])[0]))
            c = max(c, floor[j]) if floor is not None else c
            mo.tau = min(c + opts.tol, 1 - opts.tol)
        else:
            mo.tau = tolerance[j]
        mo.required = required is None or bool(required[j])
        out.append(mo)
    return out


def _motion(basis: FieldBasis, weights: MotionWeights, tg: Targets, j: int, fields: list) -> _Motion:
    """Motion j's :class:`_Motion` over ``fields`` (indices into ``basis``), its bar τ_j
    still to be set."""
    sub = weights.select_motions([j]).select_fields(fields)
    G, h = normal_equations(basis.select(fields), sub, tg.select([j], trim=True))
    return _Motion(fields, G[0], h[0], weights.P, 0.0)


def _onto_first_copies(basis: FieldBasis, own: torch.Tensor) -> tuple:
    """Candidates that equal an earlier one exactly (the same η and K: motions that took
    an earlier block's fields bring copies of them) are that earlier one: identical
    columns are one candidate. Returns (``own`` (N×M bools) with each copy's motions
    moved onto its first, whether each candidate is a first (M bools))."""
    if not basis.M:
        return own, torch.ones(0, dtype=torch.bool)
    key = torch.cat([basis.eta.detach(), basis.K().detach().flatten(1)], 1)
    _, group = torch.unique(key, dim=0, return_inverse=True)
    index = torch.arange(basis.M)
    rep = torch.full((int(group.max()) + 1,), basis.M).scatter_reduce(0, group, index, "amin")[group]
    moved = torch.zeros(own.shape, dtype=torch.long).index_add_(1, rep, own.long()) > 0
    return moved, rep == index


def _weakest(peak: torch.Tensor, own: torch.Tensor) -> float:
    """The smallest peak Gaussian on a motion's path among its own fields (1 with none):
    the scale ``reach`` is relative to. A motion made by a field centred far from its path
    (peak 2e-5, its weights large) sees the copies of that field as its own fit does."""
    return float(peak[own].min()) if bool(own.any()) else 1.0


@torch.no_grad()
def select(basis: FieldBasis, weights: MotionWeights, tg: Targets, own: torch.Tensor,
           options: Optional[SelectOptions] = None, progress=None,
           tolerance: Optional[list] = None, distributed: bool = False,
           required: Optional[list] = None, floor: Optional[list] = None) -> Selection:
    """The fewest candidates of ``basis`` found greedily that serve every motion (module
    docstring). ``weights`` hold each motion's own fit on its own candidates (``own``,
    N×M bools), giving c_j; they are left unchanged. ``tolerance``: each motion's τ_j
    instead of c_j + δ (a selection among refined fields keeps the first one's bar).
    ``progress(**values)``: called as each of this process' screening blocks ends
    (``screened="b/B blocks"``) and as each candidate joins (``chosen=m``).
    ``distributed``: the screen's blocks shared by the ranks of a run, the choice then
    made on rank 0 alone (it holds every motion's normal equations) and broadcast.
    ``required`` (N bools; None: all): the motions the chosen fields must serve; the
    others (motions their own fits did not reproduce) use what is chosen for these and
    add no field of their own: a field that only a motion no fit reproduces needs is no
    shared field. ``floor`` (N floats): each motion's c_j is at least this — the cost of
    its fewest own fields that simulation reproduces (:func:`reproducing_cost`), where its
    own fit holds more, fitting its torque targets' own error, which no other motion's
    fields need match."""
    opts = options or SelectOptions()
    among = None
    if 0 < opts.block < tg.N:
        among, tolerance = _screen(basis, weights, tg, own, opts, tolerance, distributed, progress, required,
                                   floor)

    def choose() -> Selection:
        return _select(basis, weights, tg, own, opts, progress, tolerance, among, required, floor)
    if not distributed:
        return choose()
    return parallel.broadcast(choose() if parallel.rank() == 0 else None)


def _screen(basis: FieldBasis, weights: MotionWeights, tg: Targets, own: torch.Tensor,
            opts: SelectOptions, tolerance: Optional[list], distributed: bool, progress=None,
            required: Optional[list] = None, floor: Optional[list] = None) -> tuple:
    """(the candidates that some block keeps (M bools), each motion's bar τ_j as its block
    set it): the motions in blocks of
    ``opts.block``, in order, each block's selection (:func:`_select`) among its own
    motions' fields alone. A motion's normal equations then span its block's fields and
    the blocks' choices, not every pooled field in reach: memory grows with N, not N·F².
    A field that many motions need is chosen in every block that holds some of them.
    ``distributed``: each rank chooses for its share of the blocks."""
    mine = _onto_first_copies(basis, own)[0]
    keep, bars = torch.zeros(basis.M, dtype=torch.bool), {}
    starts = list(range(0, tg.N, opts.block))
    blocks = parallel.mine(len(starts)) if distributed else range(len(starts))
    for done, b in enumerate(blocks, 1):
        part = list(range(starts[b], min(tg.N, starts[b] + opts.block)))
        sel = _select(basis, weights.select_motions(part), tg.select(part), own[part], opts, None,
                      _part(tolerance, part), mine[part].any(0), _part(required, part), _part(floor, part))
        keep[sel.kept], bars[b] = True, sel.tolerance
        if progress:
            progress(screened=f"{done}/{len(blocks)} blocks")
    if distributed:
        parts = parallel.all_gather((keep, bars))
        keep, bars = torch.stack([k for k, _ in parts]).any(0), {b: t for _, d in parts for b, t in d.items()}
    return keep, [t for b in range(len(starts)) for t in bars[b]]


def _part(values: Optional[list], motions: list) -> Optional[list]:
    """Per-motion ``values`` of ``motions`` (indices) alone; None stays None."""
    return None if values is None else [values[j] for j in motions]


def _select(basis: FieldBasis, weights: MotionWeights, tg: Targets, own: torch.Tensor,
            opts: SelectOptions, progress, tolerance: Optional[list], among: Optional[torch.Tensor],
            required: Optional[list] = None, floor: Optional[list] = None) -> Selection:
    """:func:`select` among the candidates ``among`` (M bools; None: all) and each
    motion's own."""
    motions = _motions(basis, weights, tg, own, opts, tolerance, among, required, floor)
    users = [[] for _ in range(basis.M)]
    for j, mo in enumerate(motions):
        for f in mo.fields:
            users[f].append(j)
    chosen, path = [], []
    trials: dict = {}                                 # j -> {candidate: C_j(S_j ∪ {candidate})}
    served_all = None
    while len(chosen) < basis.M:
        need = [j for j, mo in enumerate(motions) if mo.excess(mo.cost) > 0]
        if served_all is None and not need:
            served_all = len(chosen)
        if served_all is not None and len(chosen) >= served_all + opts.beyond:
            break
        gain = torch.zeros(basis.M, dtype=torch.float64)      # excess removed
        fit = torch.zeros(basis.M, dtype=torch.float64)       # cost removed
        for j in (need or range(len(motions))):
            mo = motions[j]
            if j not in trials:
                mine = [f for f in chosen if f in mo.local]
                free = [f for f in mo.fields if f not in chosen]
                trials[j] = dict(zip(free, mo.costs([mine + [f] for f in free]).tolist())) if free else {}
            for f, c in trials[j].items():
                gain[f] += (mo.excess(mo.cost) - mo.excess(c)) if need else (mo.cost - c)
                fit[f] += mo.cost - c
        best = _best(gain, fit, chosen)
        if best is None:
            break
        chosen.append(best)
        for j in users[best]:
            mo = motions[j]
            mo.cost = trials[j][best] if j in trials and best in trials[j] else float(
                mo.costs([[f for f in chosen if f in mo.local]])[0])
            trials.pop(j, None)
        path.append([len(chosen), sum(mo.cost for mo in motions),
                     sum(mo.cost <= mo.tau for mo in motions)])
        if progress:
            progress(chosen=len(chosen))
    if served_all is None:
        served_all = len(chosen)
    kept = chosen[:served_all]
    for mo in motions:                                # costs on the chosen set, not beyond
        mine = [f for f in kept if f in mo.local]
        mo.cost = float(mo.costs([mine])[0])
    kept, pruned = _prune(kept, motions, users)
    unserved = [j for j, mo in enumerate(motions) if mo.excess(mo.cost) > 0]
    costs = [mo.cost for mo in motions]
    return Selection(kept=kept, path=path, pruned=pruned, unserved=unserved,
                     support=[_fewest(mo, kept) for mo in motions], costs=costs,
                     tolerance=[mo.tau for mo in motions],
                     candidates=[mo.fields for mo in motions],
                     merged=_merged(basis, kept, motions, own))


def _fewest(mo: _Motion, kept: list) -> list:
    """Motion ``mo``'s fewest fields of ``kept``, greedily: the field that lowers C_j the
    most joins, until C_j ≤ max(τ_j, C_j on all of ``kept``) (relative 1e-9): a motion
    made by one or two fields gets those."""
    free, mine = [f for f in kept if f in mo.local], []
    bar = max(mo.tau, mo.cost) * (1 + 1e-9)
    cost = 1.0
    while free and cost > bar:
        trial = mo.costs([mine + [f] for f in free])
        best = int(torch.argmin(trial))
        mine.append(free.pop(best))
        cost = float(trial[best])
    return mine


@torch.no_grad()
def needed(basis: FieldBasis, weights: MotionWeights, tg: Targets, j: int, fields: list,
           tol: float) -> list:
    """The fewest of ``fields`` (indices into ``basis``) that motion j needs, greedily
    (:func:`_fewest`): the field that lowers C_j the most joins until C_j is within
    ``tol`` of its optimum C_j(``fields``), weights re-solved by NNLS at each size. Of
    two copies that serve the motion alike, one is needed. Returns those of ``fields``
    needed, in the order they joined."""
    if not fields:
        return []
    mo = _motion(basis, weights, tg, j, fields)
    mo.cost = float(mo.costs([fields])[0])
    mo.tau = mo.cost + tol
    return _fewest(mo, fields)


@torch.no_grad()
def reproducing_cost(basis: FieldBasis, weights: MotionWeights, tg: Targets, j: int, fields: list,
                     reproduced) -> float:
    """Motion j's relative torque cost on the fewest of ``fields`` (its own) that
    ``reproduced(basis, weights)`` accepts (a simulation), their NNLS weights re-solved:
    the fields in the order they join greedily by C_j (:func:`needed`), sizes 1, 2, …;
    where no smaller size is accepted, the cost on all of them (not checked)."""
    order = needed(basis, weights, tg, j, fields, 0.0)
    order += [f for f in fields if f not in order]
    one, cost = tg.select([j]), 1.0
    for size in range(1, len(order) + 1):
        b, w = basis.select(order[:size]), weights.select_motions([j]).select_fields(order[:size])
        cost = float(solve_weights(b, w, one)[0])
        if size < len(order) and reproduced(b, w):
            return cost
    return cost


def _merged(basis: FieldBasis, kept: list, motions: list, own: torch.Tensor) -> list:
    """[kept, dropped] pairs: each own field of a motion that was not kept, with the
    kept field nearest to it (Euclidean centre) among those its motion now uses."""
    eta, pairs = basis.eta.detach(), {}
    for j, mo in enumerate(motions):
        mine = [f for f in kept if f in mo.local]
        used = [f for f, u in zip(mine, mo.solve([mine])[1][0].tolist()) if u] if mine else []
        for f in own[j].nonzero().flatten().tolist():
            if f not in kept and f not in pairs and used:
                pairs[f] = min(used, key=lambda g: float((eta[g] - eta[f]).norm()))
    return sorted([k, f] for f, k in pairs.items())


def _best(gain: torch.Tensor, fit: torch.Tensor, chosen: list) -> Optional[int]:
    """The candidate that removes the most excess (``gain``) and, of those that remove
    as much (copies that serve the same motions equally), the one that fits them best
    (``fit``: the most cost removed); None when none removes any."""
    gain = gain.clone()
    if chosen:
        gain[chosen] = -1.0
    top = float(gain.max())
    if top <= 0:
        return None
    tied = (gain >= top * (1 - 1e-9)).nonzero().flatten()
    return int(tied[torch.argmax(fit[tied])])


def _prune(kept: list, motions: list, users: list) -> tuple:
    """Backward pruning: each kept candidate, the one fewest motions can see first,
    leaves when every motion it reaches stays served (or, if not served, no worse)
    without it. Returns (kept, pruned)."""
    pruned = []
    for f in sorted(kept, key=lambda f: (len(users[f]), -kept.index(f))):
        rest = [g for g in kept if g != f and g not in pruned]
        new = {}
        for j in users[f]:
            mo = motions[j]
            c = float(mo.costs([[g for g in rest if g in mo.local]])[0])
            if mo.excess(c) > mo.excess(mo.cost) + 1e-15 * max(mo.cost, 1e-300) or (
                    mo.excess(mo.cost) > 0 and c > mo.cost):
                break
            new[j] = c
        else:
            pruned.append(f)
            for j, c in new.items():
                motions[j].cost = c
    return [f for f in kept if f not in pruned], pruned
