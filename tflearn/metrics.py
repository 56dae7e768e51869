"""How well a model reproduces motions: simulation scored per motion, and the summaries
that metrics.json and evaluation.json hold.

For motion j simulated from its own initial state under its own torque program, the
error of a sample is e = q_sim ⊖ q_target (:func:`tflearn.physics.configspace.difference`); the
scores are the joint-angle RMSE sqrt(mean_{t,k} e²) (rad), the largest hand-tip distance
(m) and the relative RMS torque error sqrt(C_j) (:mod:`tflearn.fit.torque`). A motion
whose simulation fails (:class:`~tflearn.simulation.simulate.SimulationFailed`) scores rmse = tip =
∞ with its reason in ``failure``; the others are still scored, each on its own grid
(with ``SimOptions.batch`` ``each`` straight from the one batched simulation, which then
also lets :func:`score_models` score several models in one batch, exactly as alone).

In a run of many processes (:mod:`tflearn.parallel`) ``score(..., distributed=True)``
simulates only this rank's motions (:func:`tflearn.parallel.mine`) and gathers the
others', so that every rank holds the same scores of all motions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional, Sequence

import torch

from . import parallel
from .fit.stability import Growth
from .fit.targets import Targets, on_samples, simulate_targets
from .fit.torque import relative_rms_torque_error
from .model.fields import FieldBasis
from .model.program import FieldProgram, stack_rows
from .model.weights import MotionWeights
from .physics import dynamics
from .physics.body import Body
from .physics.configspace import difference
from .simulation.simulate import SimOptions, SimulationFailed, simulate


@dataclass
class Scores:
    """Per-motion scores of a simulation (lists of N plain floats) and the path.

    rmse (rad), tip (m), torque (relative RMS torque error), q_sim (N×T×n, NaN for a
    failed motion), failure (N: None, or why the simulation of that motion failed)."""

    rmse: list
    tip: list
    torque: list
    q_sim: torch.Tensor
    failure: list

    @classmethod
    def join(cls, parts: Sequence[Scores]) -> Scores:
        """The scores of several groups of motions (on one time grid), in order."""
        lists = {k: [x for p in parts for x in getattr(p, k)] for k in ("rmse", "tip", "torque", "failure")}
        return cls(q_sim=torch.cat([p.q_sim for p in parts]), **lists)

    def worst(self, count: Optional[int]) -> list:
        """The indices of the ``count`` motions furthest from their paths (joint RMSE; a
        failed simulation counts as furthest), worst first; None: every motion, in order."""
        if count is None:
            return list(range(len(self.rmse)))
        key = [math.inf if f is not None or not math.isfinite(r) else r
               for r, f in zip(self.rmse, self.failure)]
        return sorted(range(len(key)), key=lambda j: -key[j])[:count]

    def replaced(self, rows: Sequence[int], other: Scores) -> Scores:
        """These scores with ``rows`` (indices, in order) those of ``other``."""
        keys = ("rmse", "tip", "torque", "failure")
        out = replace(self, q_sim=self.q_sim.clone(), **{k: list(getattr(self, k)) for k in keys})
        for i, j in enumerate(rows):
            for key in keys:
                getattr(out, key)[j] = getattr(other, key)[i]
            out.q_sim[j] = other.q_sim[i, :out.q_sim.shape[1]]
        return out

    def succeeded(self, rmse: float, tip: float) -> list:
        """Per motion: simulated, joint RMSE ≤ rmse and maximum tip error ≤ tip."""
        return [f is None and r <= rmse and p <= tip
                for f, r, p in zip(self.failure, self.rmse, self.tip)]

    def off_bar(self, rmse: float, tip: float) -> list:
        """Per motion how far it lies from the bar: max(joint RMSE / rmse, tip error / tip),
        ≤ 1 where it succeeded, ∞ where its simulation failed (a bar of 0 counts as
        10⁻¹², so that errors against it still rank)."""
        rmse, tip = max(rmse, 1e-12), max(tip, 1e-12)
        return [math.inf if f is not None else max(r / rmse, p / tip)
                for f, r, p in zip(self.failure, self.rmse, self.tip)]


def path_errors(body: Body, q_sim: torch.Tensor, tg: Targets):
    """(joint RMSE (N), maximum tip distance (N)) of simulated paths against the targets."""
    e = difference(body, tg.q, q_sim)
    m = tg.mask.to(e.dtype)
    rmse = ((e ** 2).mean(-1) * m).sum(-1).div(m.sum(-1)).sqrt()
    tip = (dynamics.tip_position(body, q_sim) - dynamics.tip_position(body, tg.q)).norm(dim=-1)
    return rmse, (tip * m).amax(-1)


def _simulate_each(body, basis, weights, tg, options, until_failure=False):
    """q_sim (N×T×n) and failures (N): the batch at once, and if it fails each motion
    alone on its own grid, so that one failing motion costs only itself — with batch
    ``each`` in the same run, every motion stepped alone in it. ``until_failure``: once a
    motion alone fails, the motions after it are not simulated (failed, "not simulated")."""
    if options.batch == "each":
        return _simulate_models(body, [(basis, weights)], tg, options)[0]
    try:
        return simulate_targets(body, basis, weights, tg, options)[0], [None] * tg.N
    except SimulationFailed as err:
        if tg.N == 1:
            return torch.full_like(tg.q, float("nan")), [str(err)]
    q_sim, failure, first = torch.full_like(tg.q, float("nan")), [], None
    for j in range(tg.N):
        if until_failure and first is not None:
            failure.append(f"not simulated: {tg.names[first]} failed first")
            continue
        one = tg.select([j])
        try:
            q_sim[j] = simulate_targets(body, basis, weights.select_motions([j]), one, options)[0][0]
            failure.append(None)
        except SimulationFailed as err:
            failure.append(str(err))
            first = j if first is None else first
    return q_sim, failure


def _simulate_distributed(body, basis, weights, tg, options, until_failure=False):
    """:func:`_simulate_each` of this rank's motions, every rank's gathered (N×T×n, N)."""
    if parallel.size() == 1:
        return _simulate_each(body, basis, weights, tg, options, until_failure)
    idx, part = parallel.mine(tg.N), []
    if idx:
        q_sim, failure = _simulate_each(body, basis, weights.select_motions(idx), tg.select(idx),
                                        options, until_failure)
        part = list(zip(q_sim, failure))
    rows = parallel.gather_motions(tg.N, part)
    return torch.stack([q for q, _ in rows]).to(tg.q.device), [f for _, f in rows]


@torch.no_grad()
def score(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets,
          options: SimOptions = SimOptions(), q_sim: Optional[torch.Tensor] = None, *,
          distributed: bool = False, until_failure: bool = False) -> Scores:
    """Simulate every motion (unless ``q_sim`` is given) and score it; see the module.
    ``distributed``: share the simulations among the ranks of a run; ``until_failure``:
    where motions are simulated one by one (after a batch ``shared`` simulation failed),
    stop at the first that fails, the rest scored as failed ("not simulated: …") — all
    that a judge needs for whom any failure is a refusal (:func:`tflearn.train.no_worse`),
    without paying for the others' simulations, each as long as its evaluation budget."""
    failure = [None] * tg.N
    if q_sim is None:
        simulate = _simulate_distributed if distributed else _simulate_each
        q_sim, failure = simulate(body, basis, weights, tg, options, until_failure)
    return _scores(body, basis, weights, tg, q_sim, failure)


@torch.no_grad()
def score_models(body: Body, models: Sequence[tuple], tg: Targets, options: SimOptions) -> list:
    """:func:`score` of K models ((basis, weights) pairs, each for all of ``tg``'s motions)
    simulated in one batch of K·N members. ``options.batch`` must be ``each``: every member
    is then stepped as if alone, so each model's :class:`Scores` are exactly those that
    :func:`score` gives it alone, at about the cost of one model's simulation where
    per-call overhead dominates (small N)."""
    if options.batch != "each":
        raise ValueError("score_models: needs SimOptions(batch='each') (members stepped alone)")
    return [_scores(body, b, w, tg, *sim) for (b, w), sim in
            zip(models, _simulate_models(body, models, tg, options))]


def _simulate_models(body, models, tg, options):
    """(q_sim (N×T×n), failures (N)) of each of K models, one batch of K·N members stepped
    each alone (batch ``each``)."""
    K, N = len(models), tg.N
    program = _Stacked([FieldProgram(b, w) for b, w in models])
    base = None if tg.base is None else tg.base.take(torch.arange(N).repeat(K))
    tr = simulate(body, program, tg.q0.expand(K, -1, -1), tg.qd0.expand(K, -1, -1), tg.grid,
                  options, throw=False, base=base)
    return [(on_samples(tg, tr.q[k]), tr.failure[k * N:(k + 1) * N]) for k in range(K)]


class _Stacked(torch.nn.Module):
    """K torque programs side by side: q, v (K×N×n) and t (K×N) → τ (K×N×n), program k on
    slice k."""

    def __init__(self, programs: list):
        super().__init__()
        self.programs = torch.nn.ModuleList(programs)

    def forward(self, t, q, v):
        return torch.stack([p(t[k], q[k], v[k]) for k, p in enumerate(self.programs)])

    def rows(self, batch: torch.Size):
        """The programs' rows one after another (for the compiled simulator), or None."""
        if len(batch) < 2 or batch[0] != len(self.programs):
            return None
        parts = [p.rows(batch[1:]) for p in self.programs]
        return None if any(r is None for r in parts) else stack_rows(parts)


def _scores(body, basis, weights, tg, q_sim, failure) -> Scores:
    rmse, tip = path_errors(body, q_sim, tg)
    inf = float("inf")
    rmse = [inf if f else float(r) for f, r in zip(failure, rmse)]
    tip = [inf if f else float(p) for f, p in zip(failure, tip)]
    torque = relative_rms_torque_error(basis, weights, replace(tg, coord_weight=None)).tolist()
    return Scores(rmse, tip, torque, q_sim, failure)


#: The units of metrics.json's and evaluation.json's numbers, the documents' "units" block
#: (the keys stay unit-free; people read tip errors in cm, as 100 × tip).
UNITS = {"rmse": "rad", "tip": "m", "torque_rel_rms": "fraction of the RMS torque",
         "wall_time_s": "s", "torque_resolution": "fraction", "growth_rate": "1/s",
         "growth_efolds": "e-folds (natural log of an error's growth factor)",
         "path_stiffness": "rad/s (natural frequency of the fields' stiffness about the path)",
         "numbers": ("count (non-zero weights, onset and duration of each window in the motion, "
                     "initial state)"),
         "numbers_per_s": "1/s (numbers per second of motion)"}


def pooled_rmse(rmse: list, counts: list) -> float:
    """The joint RMSE over all samples of all motions, sqrt(Σ_j T_j rmse_j² / Σ_j T_j),
    from each motion's RMSE and its number of samples T_j (metrics.json's overall rmse)."""
    return math.sqrt(sum(r * r * c for r, c in zip(rmse, counts)) / sum(counts))


def numbers(weights: MotionWeights, tg: Targets, nv: int) -> torch.Tensor:
    """(N,) how many numbers describe each motion on its basis: its non-zero weights, the
    onset and duration of each window that starts inside it, and its initial state (2 nv)."""
    used = (weights.vector().abs() > 0).sum(-1)
    inside = (weights.window_onset < tg.duration[:, None]).sum(-1)
    return (used + 2 * inside + 2 * nv).to(tg.duration.dtype)


def summarize(scores: Scores, ok: list, tg: Targets, M: int, wall: float, growth: Growth,
              stiffness: torch.Tensor, count: torch.Tensor) -> dict:
    """metrics.json's content: per motion and overall joint RMSE (rad), maximum tip error
    (m), relative RMS torque error, the local error growth along the path (``growth``,
    :mod:`tflearn.fit.stability`: peak rate, e-folds), the fields' stiffness about the
    path (``stiffness`` N, :func:`tflearn.fit.impedance.path_stiffness`: 0 where they push
    the limb off it), the numbers that describe each motion and their rate per second of
    motion (``count`` N, :func:`numbers`), success, and the failure of a failed simulation, and the units of
    these numbers (:data:`UNITS`). The overall RMSE is over all samples of all motions;
    the overall growth the largest, the overall stiffness the least, the overall rate the
    largest."""
    per = {}
    peak, efolds, held = growth.peak.tolist(), growth.efolds.tolist(), stiffness.tolist()
    rate = (count / tg.duration).tolist()
    for j, name in enumerate(tg.names):
        per[name] = {"rmse": scores.rmse[j], "tip": scores.tip[j],
                     "torque_rel_rms": scores.torque[j], "growth_rate": peak[j],
                     "growth_efolds": efolds[j], "path_stiffness": held[j], "numbers": int(count[j]),
                     "numbers_per_s": rate[j], "success": ok[j]}
        if scores.failure[j]:
            per[name]["failure"] = scores.failure[j]
    return {"motions": per,
            "overall": {"rmse": pooled_rmse(scores.rmse, tg.mask.sum(-1).tolist()), "tip": max(scores.tip),
                        "torque_rel_rms": max(scores.torque), "growth_rate": max(peak),
                        "growth_efolds": max(efolds), "path_stiffness": min(held),
                        "numbers_per_s": max(rate), "success": all(ok),
                        "M": M, "wall_time_s": wall},
            "units": dict(UNITS)}
