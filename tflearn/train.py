"""The training pipeline behind ``train CONFIG``: motions → torques → fit → basis → metrics.

A run goes through an explicit sequence of stages (:data:`SEQUENCES`), each unit of work
ending in an atomically written checkpoint, so that a run killed at any moment and
started again with the same command resumes at the last unit and ends with the same
result:

1. ``each``   — every motion alone: greedy growth of its own fields from data-driven,
                seeded multi-start candidates, refined by EM, until its relative torque
                cost is below ``solver.each.tol`` and simulation reproduces it (one unit
                per motion);
2. ``pool``   — all per-motion fields in one basis, every motion's weights re-solved
                over all of them (so no motion fits worse than alone; with
                ``solver.pool.sharing: own`` each motion keeps to its own fields, as it
                was reproduced alone); fields that nearly coincide (``solver.merge``)
                merged and refined jointly by EM;
3. ``reduce`` — backward elimination: drop each field in turn (smallest share first)
                and keep it dropped if no motion gets worse by simulation
                (:func:`no_worse`) — the smallest M found is reported (one unit per
                field tried); with ``sharing: own`` a motion that loses one of its
                fields may then use every field left;
4. ``path``   — path matching for motions not yet reproduced: first each one's
                weights (and with ``model.phases: variable`` its timing) by multiple
                shooting and Levenberg–Marquardt, the basis fixed
                (``solver.shooting``, :mod:`tflearn.fit.shooting`; one unit, the
                motions shared by the ranks), then, if some are still not
                reproduced, safeguarded Adam on the simulated path loss of fields and
                weights through ``odeint`` (one unit per step);
5. ``rescue`` — with ``solver.rescue.enabled`` only: motions still not reproduced get a
                spanning layout's fields laid out around them added to the basis, their
                weights by NNLS on those fields, then multiple shooting over the whole
                basis (``solver.rescue``'s settings); a motion keeps the new program if
                it reproduces it or comes closer, and those still not reproduced get a
                layout of their own in the next round (one unit per round, at most
                ``solver.rescue.rounds``, until a round improves none);
6. ``done``   — ``basis.json``, ``metrics.json``, ``config.yaml``, figures, TensorBoard.

What the run shows and logs meanwhile (progress bars, TensorBoard) is :mod:`tflearn.log`.

With ``solver.method: slsqp`` the single stage ``slsqp`` replaces 1–4: the thesis'
baseline (:func:`tflearn.fit.slsqp.fit_slsqp`, torque matching only) with
``model.fields`` diagonal-stiffness fields from a seeded random guess — centres at
postures drawn from the motions' samples, K = I, weights by NNLS.
With ``solver.method: layout`` the stage ``layout`` replaces 1–3: the spanning fields of
:func:`tflearn.fit.layout.spanning_basis` around all the motions, every motion's
weights by NNLS; ``path`` follows as above.

The run's state is a :class:`RunState`; checkpoints hold it as plain tensors and JSON
values only (loaded with ``torch.load(weights_only=True)``).

Many processes (``torchrun --nproc-per-node N -m tflearn.cli train CONFIG``, see
:mod:`tflearn.parallel` and docs/parallel.md): ``each`` fits motions in rounds of one
motion per rank; every simulation that scores the shared model, path matching's loss
and gradient, and EM's weight solves and Gauss–Newton sums are shared by motion
(:func:`tflearn.parallel.shard`), and the results are gathered or summed, so that every
rank holds the same state and takes the same decisions; SLSQP runs whole on every
rank. Rank 0 alone reads and writes the checkpoint (the state is global: a run resumes
with any number of ranks) and writes the artefacts, the progress display and
TensorBoard. Motion j's own search draws from its own generator,
seeded from the run's generator and j, so that its result does not depend on which
rank fits it or on the other motions.
"""
from __future__ import annotations

import contextlib
import json
import math
import time
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from types import SimpleNamespace
from typing import Optional

import torch

from . import config as config_mod
from . import parallel
from .config import Config, ConfigError
from .data.loading import check_resolution, load_motions, torsos
from .errors import InputError
from .fit import layout, search, shooting, slsqp, stability, torque
from .fit import path as path_fit
from .fit.targets import Targets, inertia_weights, prepare, submovement_windows
from .io import basis as basis_io
from .io.files import replacing, write_text
from .log import RunLog
from .metrics import Scores, score, score_models, summarize
from .mocap import clips as mocap
from .model.fields import FieldBasis, MotionWeights, model_from_state, model_state
from .physics.body import from_config
from .simulation import simulate as sim_mod

CHECKPOINT_FORMAT = "tflearn-checkpoint/5"
SEQUENCES = {"pipeline": ("each", "pool", "reduce", "path", "rescue", "done"),
             "slsqp": ("slsqp", "done"),
             "layout": ("layout", "path", "done")}


class Interrupted(Exception):
    """Raised by :func:`run` after ``stop_after`` checkpoints (used to test resuming)."""


class CheckpointError(InputError):
    """A checkpoint that cannot be resumed; the message names the file and the problem."""


@dataclass
class RunState:
    """Everything a run needs to resume: where it is (stage, cursor within the stage),
    the random generator, the per-motion fits of ``each``, the current model
    (:func:`~tflearn.model.fields.model_state`), the reference scores and torque costs of
    ``reduce`` and its elimination order, path matching's optimizer and best point, the history
    reported in metrics.json, and the compute time and simulations spent so far."""

    config: dict
    stage: str
    rng: torch.Tensor
    cursor: int = 0
    step: int = 0
    elapsed: float = 0.0
    simulations: int = 0                               # this process' (rank 0's), over resumes
    fits: list = field(default_factory=list)          # [(η, K, timing and weights)]: until pool
    model: Optional[dict] = None
    history: dict = field(default_factory=dict)
    reference: Optional[dict] = None                   # {"rmse", "tip", "ok", "cost"} per motion
    order: Optional[list] = None                       # reduce: fields by share
    ids: Optional[list] = None                         # reduce: original ids kept
    path: Optional[dict] = None                        # {"needed", "lr", "optimizer", "best"}
    support: Optional[list] = None                     # N×M: fields each motion may use, or all

    def to_dict(self) -> dict:
        """The fields as they are, not copied (``torch.save`` writes them at once): a deep
        copy of a thousand motions' state cost a second per checkpoint."""
        return {"format": CHECKPOINT_FORMAT, **{f.name: getattr(self, f.name) for f in fields(self)}}

    @classmethod
    def from_dict(cls, doc: dict, where: str) -> RunState:
        if not isinstance(doc, dict) or doc.get("format") != CHECKPOINT_FORMAT:
            found = doc.get("format") if isinstance(doc, dict) else None
            raise CheckpointError(f"{where}: a checkpoint of another tflearn version (format "
                                  f"{found!r}, this version reads {CHECKPOINT_FORMAT!r}); "
                                  f"pass --restart to start afresh")
        doc = {k: v for k, v in doc.items() if k != "format"}
        try:
            return cls(**doc)
        except TypeError as err:
            raise CheckpointError(f"{where}: not a complete checkpoint ({err}); pass --restart") from None


def no_worse(reference: dict, scores: Scores, ok: list) -> bool:
    """Whether a smaller basis keeps every motion as good as ``reference`` ({"rmse",
    "tip", "ok"}, per motion): a motion reproduced stays reproduced; one not reproduced is
    still simulated and has joint RMSE and tip error no larger than before (a failed
    simulation is never "no worse", whatever the reference: ∞ ≤ ∞ does not count)."""
    return all(now if was else (f is None and r <= r0 and p <= p0)
               for was, now, f, r, r0, p, p0 in zip(reference["ok"], ok, scores.failure, scores.rmse,
                                                    reference["rmse"], scores.tip, reference["tip"]))


def _reference(scores: Scores, ok: list) -> dict:
    return {"rmse": list(scores.rmse), "tip": list(scores.tip), "ok": list(ok)}


def _weight_support(fields: Optional[list], P: int) -> Optional[torch.Tensor]:
    """The weights (N×M(2+P) bools, [a | b | c]) of the fields each motion may use
    (N×M lists of bools, :attr:`RunState.support`); None: every weight free."""
    if fields is None:
        return None
    f = torch.tensor(fields, dtype=torch.bool).reshape(len(fields), -1)
    return torch.cat([f, f, f.repeat_interleave(P, dim=1)], dim=1)


# ------------------------------------------------------------------------------ the run

class Run:
    """One training run: owns the config, the data, the log (:class:`~tflearn.log.RunLog`)
    and the checkpoint."""

    def __init__(self, cfg: Config, stop_after: int | None = None, progress: bool | None = None):
        cfg, self.imported = mocap.import_config(cfg)  # data naming BVH clips: imported first
        self.cfg = cfg
        self.out = Path(cfg.out)
        self.body = from_config(cfg.body)          # checked when the config was validated
        self.device = run_device(cfg.device)
        self.options = cfg.solver.path.options()
        self.stop_after = stop_after
        self.checkpoints = 0
        self._window = 1                             # reduce: trials checked together
        self._checked = None                         # _check: (key, scores) of the last one
        self._t0, self._calls0 = time.time(), sim_mod.calls   # what save() counts from
        self._fields_before = (0, None)              # each: (upto, library) of _library
        self.progress = cfg.log.progress if progress is None else progress
        self.ckpt_path = self.out / "checkpoint.pt"
        self.log = RunLog(self.out, tensorboard=False, progress=False)
        self.stages = {"each": self._each, "pool": self._pool, "reduce": self._reduce,
                       "path": self._path, "rescue": self._rescue, "slsqp": self._slsqp,
                       "layout": self._layout}
        self.sequence = tuple(x for x in SEQUENCES[cfg.solver.method]
                              if x != "rescue" or cfg.solver.rescue.enabled)
        if cfg.solver.method == "layout" and (cfg.model.stiffness == "scalar" or cfg.model.fields):
            raise ConfigError("solver.method 'layout' lays out its fields with a stiffness per "
                              "coordinate: it needs model.fields=0 and model.stiffness diag, block "
                              f"or full (got {cfg.model.fields}, {cfg.model.stiffness!r})")
        if cfg.solver.method == "slsqp":
            m = cfg.model
            if (m.fields < 1 or m.stiffness != "diag" or m.phases != "fixed" or m.field_damping
                    or m.windows or cfg.solver.torque_weight != "uniform"):
                raise ConfigError(
                    "solver.method 'slsqp' (the thesis' baseline) fits a basis of a given size "
                    "with diagonal stiffness, fixed phases, no field damping and no windows: it "
                    "needs model.fields ≥ 1, model.stiffness=diag, model.phases=fixed, "
                    f"model.field_damping=0, model.windows=0 and solver.torque_weight=uniform "
                    f"(got {m.fields}, {m.stiffness!r}, {m.phases!r}, {m.field_damping}, "
                    f"{m.windows}, {cfg.solver.torque_weight!r})")

    def template(self) -> FieldBasis:
        """An empty basis of the configured kind and field damping on the body's blocks."""
        return empty_basis(self.cfg, self.body)

    # ---- checkpoints
    def save(self, state: RunState):
        """Write the checkpoint (rank 0; every rank counts it for ``stop_after``)."""
        state.elapsed += time.time() - self._t0
        state.simulations += sim_mod.calls - self._calls0
        self._t0, self._calls0 = time.time(), sim_mod.calls
        if parallel.rank() == 0:
            self._write_checkpoint(state)
        self.checkpoints += 1
        if self.stop_after is not None and self.checkpoints >= self.stop_after:
            raise Interrupted(f"stopped after {self.checkpoints} checkpoints")

    def _write_checkpoint(self, state: RunState) -> None:
        with replacing(self.ckpt_path) as tmp:
            torch.save(state.to_dict(), tmp)

    def load(self) -> Optional[RunState]:
        if not self.ckpt_path.exists():
            return None
        try:
            doc = torch.load(self.ckpt_path, weights_only=True, map_location=self.device)
        except Exception as err:
            raise CheckpointError(f"{self.ckpt_path}: not a readable checkpoint "
                                  f"({type(err).__name__}); pass --restart to start afresh") from None
        state = RunState.from_dict(doc, str(self.ckpt_path))
        # a key the checkpoint lacks was added to the config after it was written: it ran
        # as that key's default does (a new key's default keeps the old behaviour)
        old = config_mod.merge(type(self.cfg)().model_dump(), state.config)
        changed = config_changes(old, self.cfg.model_dump())
        if changed:
            raise CheckpointError(
                f"{self.ckpt_path}: a checkpoint of a different config is in this output folder "
                f"({', '.join(changed[:5])}{', …' if len(changed) > 5 else ''} differ); "
                f"choose another out= or pass --restart")
        return state

    def _start(self, restart: bool) -> Optional[RunState]:
        """Rank 0's checkpoint (or None) on every rank; a bad one raises on every rank."""
        state, error = None, None
        if parallel.rank() == 0:
            self.out.mkdir(parents=True, exist_ok=True)
            if restart:
                self.ckpt_path.unlink(missing_ok=True)
            try:
                state = self.load()
            except CheckpointError as err:
                error = str(err)
        state, error = parallel.broadcast((state, error))
        if error:
            raise CheckpointError(error)
        return state

    # ---- stages
    def execute(self, restart: bool = False) -> dict:
        """The run in this process: alone, or as one rank of the process group torchrun
        describes (:func:`tflearn.parallel.group`)."""
        with parallel.group(str(self.device)):
            return self._execute(restart)

    def _execute(self, restart: bool) -> dict:
        torch.manual_seed(self.cfg.seed)
        self._t0, self._calls0 = time.time(), sim_mod.calls
        motions = load_motions(self.cfg.data, self.body, strict=self.cfg.strict)
        self.resolution = check_resolution(self.body, motions)
        tg = prepare(self.body, motions, weight=self.cfg.solver.torque_weight,
                     base=torsos(self.cfg.data, motions, self.cfg.torso))
        with on_device(self.device):
            return self._stages(restart, tg.to(self.device))

    def _stages(self, restart: bool, tg: Targets) -> dict:
        state = self._start(restart)
        if state is None:
            gen = torch.Generator().manual_seed(self.cfg.seed)
            state = RunState(config=self.cfg.model_dump(), stage=self.sequence[0], rng=gen.get_state())
        lead = parallel.rank() == 0
        self.log = RunLog(self.out, tensorboard=self.cfg.log.tensorboard and lead,
                          progress=self.progress and lead, body=self.body, sequence=self.sequence,
                          figures=self.cfg.log.figures)
        if self.imported is not None:
            self.log.message(f"imported {len(self.imported['clips'])} BVH clip(s) into {self.cfg.data} "
                             f"(report.json there); body: the performer's arm")
        if state.step or state.stage != self.sequence[0]:
            self.log.message(f"resuming {self.out} at stage {state.stage} ({state.cursor})")
        with self.log:
            self.log.open(state.step)
            while state.stage != "done":
                self.stages[state.stage](state, tg)
            return self.finish(state, tg)

    def _gen(self, state: RunState) -> torch.Generator:
        gen = torch.Generator()
        gen.set_state(state.rng.cpu())              # a checkpoint's tensors load on the run's device
        return gen

    def _advance(self, state: RunState):
        state.stage = self.sequence[self.sequence.index(state.stage) + 1]
        state.cursor = 0

    def _check(self, basis, weights, tg: Targets, distributed: bool = True, until_failure: bool = False):
        """(scores, success per motion); ``distributed``: the simulations shared by the
        ranks (every rank gets all motions' scores), else simulated here;
        ``until_failure``: for a judge that refuses any failure (:func:`~tflearn.metrics.score`).
        The same model checked again on the same targets is not simulated again."""
        key = (tg, model_state(basis, weights), distributed, until_failure)
        if self._checked is None or not _same_check(self._checked[0], key):
            scores = score(self.body, basis, weights, tg, self.options, distributed=distributed,
                           until_failure=until_failure)
            self._checked = (key, scores)
        scores = self._checked[1]
        return scores, scores.succeeded(self.cfg.success.rmse, self.cfg.success.tip)

    def _tick(self, state: RunState) -> int:
        """The step of a new log entry (steps only grow, across a resumed run too)."""
        state.step += 1
        return state.step

    def _em(self, basis, weights, tg, state: RunState, tag: str | None = None, support=None,
            min_gain: float = 0.0):
        """EM refinement; ``tag``: log the summed torque cost at every step under it;
        ``support``: the fields each motion may use (N×M lists of bools), None for all;
        ``min_gain``: :func:`tflearn.fit.torque.em`'s."""
        c = self.cfg.solver.em

        def cb(step, costs):
            self._tick(state)
            cost = float(costs.sum())
            if tag:
                self.log.scalar(tag, cost, state.step)
            self.log.busy(em_step=step + 1, cost=cost)
        return torque.em(basis, weights, tg, steps=c.steps, tol=c.tol, max_step=c.max_step,
                         phases=self.cfg.model.phases == "variable", callback=cb, distributed=True,
                         support=_weight_support(support, weights.P), min_gain=min_gain)

    def _each(self, state: RunState, tg: Targets):
        """One round: the motions from the cursor to the end of its block of
        ``solver.each.reuse`` (without reuse, one per rank), each fitted alone
        (:meth:`_fits`), gathered in motion order, then one checkpoint."""
        j = state.cursor
        self.log.stage("each", tg.N, j)
        gen = self._gen(state)
        # motion k's search: seeds[k] (drawn on the CPU: the same seeds on any device)
        seeds = torch.randint(2 ** 62, (tg.N,), generator=gen, device="cpu").tolist()
        if j >= tg.N:
            state.rng = gen.get_state()
            self.log.end_stage()
            return self._advance(state)
        B = self.cfg.solver.each.reuse
        batch = list(range(j, min(tg.N, (j // B + 1) * B if B else j + parallel.size())))
        fits = self._fits(self._library(state, tg, B * (j // B) if B else 0), tg, batch, seeds)
        alone = state.history.setdefault("each", {"reproduced": [], "reused": [], "declined": {}})
        for k, fit in zip(batch, fits):
            state.fits.append(fit["fit"])
            alone["reproduced"].append(fit["reproduced"])
            if fit.get("reused"):
                alone["reused"].append(tg.names[k])
            if fit.get("declined"):
                alone.setdefault("declined", {})[tg.names[k]] = fit["declined"]
            step = self._tick(state)
            if fit["scores"] is not None:
                one = tg.select([k])
                self.log.scalar("torque_cost/each", fit["cost"], step)
                figures = self.cfg.log.figures is None or k < self.cfg.log.figures
                self.log.scores(fit["scores"], one, step, figures=figures, overview=False)
                self.log.fields(sum(f[1].shape[0] for f in state.fits), step,
                                torch.cat([f[1] for f in state.fits]), fit["weights"])
            self.log.status(motion=tg.names[k], M=fit["M"], cost=fit["cost"],
                            reproduced=fit["reproduced"], reused=len(alone["reused"]))
        state.cursor = batch[-1] + 1
        self.save(state)

    def _library(self, state: RunState, tg: Targets, upto: int) -> Optional[FieldBasis]:
        """The fields fitted for motions 0 … ``upto`` − 1, near-duplicates merged
        (:func:`~tflearn.fit.search.merge_close`), for ``solver.each.reuse``; None when
        there are none. Kept until ``upto`` changes."""
        if not upto:
            return None
        if self._fields_before[0] != upto:
            fits, merge = state.fits[:upto], self.cfg.solver.merge
            basis = self.template().like(torch.cat([f[0] for f in fits]), torch.cat([f[1] for f in fits]))
            stub = MotionWeights.zeros(basis.M, tg.duration[:1])
            self._fields_before = (upto, search.merge_close(basis, stub, merge.distance, merge.stiffness)[0])
        library = self._fields_before[1]
        return library if library.M else None

    def _fits(self, library: Optional[FieldBasis], tg: Targets, batch: list, seeds: list) -> list:
        """The fits of motions ``batch`` in the per-motion stage, in order: each on the
        ``library``'s fields where they do (:meth:`_reuse`), the motions shared by the
        ranks; then the declined ones' own searches (:meth:`_fit_one`, each recording why
        the library did not do, ``"declined"``), shared by the ranks in turn, so that
        each rank gets as many of the costly searches as the others."""
        tries = [(None, None)] * len(batch) if library is None else parallel.gather_motions(
            len(batch), [self._reuse(library, tg, batch[i]) for i in parallel.mine(len(batch))])
        todo = [i for i, (fit, _) in enumerate(tries) if fit is None]
        own = parallel.gather_motions(len(todo), [self._fit_one(tg, batch[todo[i]], seeds[batch[todo[i]]])
                                                  for i in parallel.mine(len(todo))])
        fits = [fit for fit, _ in tries]
        for i, fit in zip(todo, own):
            fits[i] = {**fit, "declined": tries[i][1]}
        return fits

    def _reuse(self, library: Optional[FieldBasis], tg: Targets, k: int):
        """Motion k on the ``library``'s fields (:meth:`_library`): its NNLS weights over
        them; if its relative torque cost is within ``solver.each.reuse_tol`` (unset:
        ``solver.each.tol``) and simulation reproduces it, (its fit (as :meth:`_fit_one`'s)
        on the fields it uses, None), else (None, why not: a line naming the cost or the
        simulation's errors; None without a library)."""
        if library is None:
            return None, None
        one = tg.select([k])
        self.log.busy(motion=tg.names[k], reusing=library.M)
        w = MotionWeights.zeros(library.M, one.duration, one.names,
                                submovement_windows(one, self.cfg.model.windows))
        each = self.cfg.solver.each
        tol = each.tol if each.reuse_tol is None else each.reuse_tol
        cost = float(torque.solve_weights(library, w, one)[0])
        used = w.used()[0].nonzero().flatten().tolist()
        if not used or not cost <= tol:
            return None, f"torque cost {cost:.3g} > {tol:g} on {len(used)} of {library.M} fields"
        basis, w = library.select(used), w.select_fields(used)
        scores, ok = self._check(basis, w, one, distributed=False)
        if not all(ok):
            why = scores.failure[0] or f"rmse {scores.rmse[0]:.3g} rad, tip {100 * scores.tip[0]:.3g} cm"
            return None, f"simulation on {len(used)} fields (torque cost {cost:.3g}): {why}"
        board = self.cfg.log.tensorboard
        return {"fit": (basis.eta.detach().clone(), basis.K().detach().clone(), w.timing(0, weights=True)),
                "cost": cost, "M": basis.M, "reproduced": True, "reused": True,
                "scores": scores if board else None, "weights": w if board else None}, None

    def _fit_one(self, tg: Targets, k: int, seed: int) -> dict:
        """Motion k's own search (:func:`tflearn.fit.search.grow`) with a generator
        seeded ``seed``: its fit (η, K, timing), cost, M, whether simulation reproduces
        it, and for TensorBoard its scores and weights."""
        c, m = self.cfg.solver, self.cfg.model
        one = tg.select([k])
        self.log.busy(motion=tg.names[k])
        checked = {}

        def reproduced(b, w):
            checked["last"] = (b, *self._check(b, w, one, distributed=False))
            return all(checked["last"][2])
        b, w, costs = search.grow(one, self.template(), c.each.max_fields, c.each.tol,
                                  c.init.candidates, c.init.stiffness_grid,
                                  torch.Generator().manual_seed(seed), c.em.steps,
                                  phases=m.phases == "variable", em_tol=c.em.tol,
                                  reproduced=reproduced,
                                  windows=submovement_windows(one, m.windows))
        if b.M and checked.get("last", (None,))[0] is not b:
            reproduced(b, w)                         # grow stopped before checking its last basis
        if b.M and not all(checked["last"][2]) and self._shoot_alone(b, w, one, reproduced):
            costs = torque.torque_cost(b, w, one).detach()
        last = checked.get("last")
        fresh = last is not None and last[0] is b
        scores = None
        if self.cfg.log.tensorboard:
            scores = last[1] if fresh else self._check(b, w, one, distributed=False)[0]
        return {"fit": (b.eta.detach().clone(), b.K().detach().clone(), w.timing(0, weights=True)),
                "cost": float(costs[0]), "M": b.M, "reproduced": bool(fresh and all(last[2])),
                "scores": scores, "weights": w if self.cfg.log.tensorboard else None}

    def _shoot_alone(self, basis, weights, one: Targets, reproduced) -> bool:
        """A motion its own fields do not reproduce: those fields and its weights fitted
        to its path by multiple shooting (``solver.shooting.fields``; docs/model.md,
        "Programs whose motion is chaotic"), in place, then checked by ``reproduced``.
        Returns whether it ran."""
        c = self.cfg.solver.shooting
        if not (c.fields and c.iterations):
            return False
        self.log.busy(shooting="fields")
        opts = replace(c.options(self.cfg.model.phases == "variable"), fields=True)
        shooting.shooting_match(self.body, basis, weights, one, options=opts, sim=self.options)
        reproduced(basis, weights)
        return True

    def _pool(self, state: RunState, tg: Targets):
        merge = self.cfg.solver.merge
        self.log.stage("pool", 1)
        basis, weights = search.pool(tg, state.fits, self.template())
        if self.cfg.solver.pool.sharing == "own":       # each motion on its own fields
            ends = torch.tensor([len(f[0]) for f in state.fits]).cumsum(0).tolist()
            state.support = [[lo <= i < hi for i in range(basis.M)] for lo, hi in zip([0] + ends, ends)]
        basis, weights, merged = search.merge_close(basis, weights, merge.distance, merge.stiffness)
        if merged and state.support is not None:        # a merged cluster: its motions may use it
            drop = {k for _, k in merged}
            for row in state.support:
                for i, k in merged:
                    row[i] = row[i] or row[k]
            state.support = [[x for i, x in enumerate(row) if i not in drop] for row in state.support]
        if merged or self.cfg.model.phases == "variable":   # other motions' phases: default
            self._em(basis, weights, tg, state, tag="torque_cost/pool", support=state.support,
                     min_gain=self.cfg.solver.pool.min_gain)
        cost = float(torque.solve_weights(basis, weights, tg,
                                          _weight_support(state.support, weights.P)).sum())
        scores, ok = self._adopt(state, tg, "pool", basis, weights, cost, merged=merged)
        scores, ok = self._restore(state, tg, scores, ok)
        state.fits = []                              # read by no later stage: not saved again
        state.reference = _reference(scores, ok)
        if self.cfg.solver.reduce.growth is not None:
            state.reference["efolds"] = self._efolds(*model_from_state(state.model), tg)
        pooled = state.history["pool"]
        self.log.status(M=pooled["M"], merged=len(merged), cost=cost,
                        restored=len(pooled.get("restored", [])), reproduced=f"{sum(ok)}/{tg.N}")
        self.log.end_stage()
        self._advance(state)
        self.save(state)

    def _restore(self, state: RunState, tg: Targets, scores: Scores, ok: list) -> tuple:
        """Motions their own fits reproduced (the ``each`` stage) that the pooled model
        does not — merging or refitting moved a field their path needs to the digit —
        get their own fields back as fields of their own: such a motion's weights and
        timing are its own fit's, on those fields only, and no other motion uses them
        (:attr:`RunState.support`); elimination may still remove them, by its rule.
        Changes ``state.model`` and ``state.support``; returns the (scores, success) of
        every motion."""
        alone = state.history.get("each", {}).get("reproduced", [])
        broken = [j for j, (a, o) in enumerate(zip(alone, ok)) if a and not o]
        if not broken:
            return scores, ok
        basis, weights = model_from_state(state.model)
        M0, own = basis.M, [state.fits[j] for j in broken]
        nb = basis.extend(torch.cat([f[0] for f in own]), torch.cat([f[1] for f in own]))
        nw = weights.extend_fields(nb.M - M0)
        rows = state.support or [[True] * M0 for _ in range(tg.N)]
        support = [row + [False] * (nb.M - M0) for row in rows]
        start = M0
        with torch.no_grad():
            for j, (eta, _, fit) in zip(broken, own):
                for key in ("a_raw", "b_raw", "c_raw"):
                    getattr(nw, key)[j] = 0.0
                for key, row in fit.items():
                    target = getattr(nw, key)
                    if key in MotionWeights.WINDOWS:
                        target[j] = row
                    else:
                        target[j, start:start + len(eta)] = row
                support[j] = [start <= i < start + len(eta) for i in range(nb.M)]
                start += len(eta)
        check, fine = self._check(nb, nw.select_motions(broken), tg.select(broken))
        scores = replace(scores, q_sim=scores.q_sim.clone(),
                         **{k: list(getattr(scores, k)) for k in ("rmse", "tip", "torque", "failure")})
        ok = list(ok)
        for i, j in enumerate(broken):
            for key in ("rmse", "tip", "torque", "failure"):
                getattr(scores, key)[j] = getattr(check, key)[i]
            scores.q_sim[j] = check.q_sim[i, :scores.q_sim.shape[1]]
            ok[j] = fine[i]
        state.model, state.support = model_state(nb, nw), support
        state.history["pool"].update(M=nb.M, success=ok, restored=[tg.names[j] for j in broken])
        self.log.model(nb, nw, self._tick(state))
        return scores, ok

    def _reduce(self, state: RunState, tg: Targets):
        """Backward elimination. With model.fields = 0 a field goes only if no motion gets
        worse (:func:`no_worse`), a field no motion uses goes as it is (:meth:`_idle`),
        and a field that a motion not reproduced uses is kept without a trial
        (:meth:`_carried`); any other is tried first with every field refitted by EM (:meth:`_trial`;
        ``solver.reduce.refit``), then, if that breaks a motion or refitting is off, with
        every other field held where it is (:meth:`_held_trial`: only the motions that
        used it re-solve their weights and are simulated again); with model.fields = M
        the smallest-share fields go until M remain (refitted). With
        ``solver.path.batch: each`` (one process) the refitted trials of the next fields
        are checked together in one simulation
        (:func:`~tflearn.metrics.score_models`) and applied in order up to the first
        removal, the rest dropped: the same decisions as one at a time, since each
        motion's simulation is then independent of its batch; the window doubles after
        trials that all keep their field, and starts again at one after a removal."""
        fixed = self.cfg.model.fields
        basis, weights = model_from_state(state.model)
        if state.order is None:
            shares = search.field_shares(basis, weights, tg)
            state.order = [int(i) for i in torch.argsort(shares)]
            state.ids = list(range(basis.M))
        if "cost" not in state.reference:            # kept up to date by _apply_trial
            state.reference["cost"] = torque.torque_costs(basis, weights, tg).tolist()
        k = state.cursor
        floor = max(fixed, 1)

        def total(M):                        # fields to try: at most one per field, until M = floor
            return min(len(state.order), k + max(M - floor, 0))
        self.log.stage("reduce", total(basis.M), k)
        if basis.M <= floor or k >= len(state.order):
            self.log.end_stage()
            return self._advance(state)
        refit = fixed or self.cfg.solver.reduce.refit
        together = refit and not fixed and self.options.batch == "each" and parallel.size() == 1
        window = self._window if together else 1
        victims = state.order[k:total(basis.M)][:window]
        carried = set() if fixed else self._carried(weights, state)
        idle = set() if fixed else self._idle(weights, state)
        if victims[0] in carried:                    # kept without a trial
            self._apply_trial(state, self._kept(victims[0]), tg, total)
            return
        if victims[0] in idle:                       # removed as it is: nothing changes
            self._apply_trial(state, self._held_trial(basis, weights, tg, state, victims[0]), tg, total)
            return
        victims = victims[:next((i for i, v in enumerate(victims) if v in carried | idle), len(victims))]
        trials = [self._trial(basis, weights, tg, state, victim) for victim in victims] if refit else []
        checks = ([None] * len(trials) if fixed or not trials
                  else self._checks([t["model"] for t in trials], tg))
        for i, victim in enumerate(victims):         # each field: refitted, else held
            trial = {**trials[i], "check": checks[i]} if refit else None
            if not (refit and self._accepts(state, trial, tg)) and not fixed:
                held = self._held_trial(basis, weights, tg, state, victim)
                trial = held if self._accepts(state, held, tg) or not refit else trial
            if self._apply_trial(state, trial, tg, total):
                self._window = 1
                return
        self._window = 2 * window

    @staticmethod
    def _carried(weights, state: RunState) -> set:
        """The fields (ids) that a motion not reproduced, but simulated to its end, has a
        weight on. Elimination keeps them: such a motion's path is still to be matched
        (multiple shooting, the path stage), which needs its fields, and its simulation,
        already off the path, cannot show what losing one costs (a removal judged by it
        left straight_reach with two fields that shooting could not carry). The fields of
        a motion whose simulation fails are still tried: a removal that lets it be
        simulated is one that path matching needs."""
        used = weights.used()
        ref = state.reference
        off = torch.tensor([not ok and math.isfinite(r) for ok, r in zip(ref["ok"], ref["rmse"])])
        return {state.ids[i] for i in used[off].any(0).nonzero().flatten().tolist()}

    @staticmethod
    def _idle(weights, state: RunState) -> set:
        """The fields (ids) on which no motion has a weight: removed without a refit (its
        held trial changes no motion's torques, so it needs no simulation either)."""
        return {state.ids[i] for i in (~weights.used().any(0)).nonzero().flatten().tolist()}

    @staticmethod
    def _kept(victim: int) -> dict:
        """The record of a field kept without a trial (:meth:`_carried`)."""
        return {"victim": victim, "model": None, "cost": None, "em_steps": 0, "check": None,
                "trial": "none", "refused": "used by a motion not reproduced"}

    def _held_trial(self, basis, weights, tg: Targets, state: RunState, victim: int) -> dict:
        """The basis without field ``victim``, every other field held: the motions with a
        weight on it (a, b or c) get their weights re-solved by NNLS over the fields left
        and are checked by simulation; the others keep their weights, paths and scores."""
        pos, keep, nb, nw, support = self._without(basis, weights, state, victim, tg)
        users = weights.used()[:, pos].nonzero().flatten().tolist()
        self.log.busy(M=basis.M, holding=victim, motions=len(users))
        check = None
        costs = state.reference["cost"]
        if users:
            sub, one = nw.select_motions(users), tg.select(users)
            after = torque.solve_weights(nb, sub, one, None if support is None else
                                         _weight_support([support[j] for j in users], nw.P))
            keys = ("a_raw", "b_raw", "c_raw")
            nw.set_flat(keys, sub.flat(keys), users)
            costs = costs.copy()
            for j, x in zip(users, after.tolist()):
                costs[j] = x
            users, check = self._held_check(state, users, (nb, sub), one, after)
        return {"victim": victim, "keep": keep, "model": (nb, nw), "support": support,
                "cost": math.fsum(costs), "costs": costs, "em_steps": 0, "check": check, "motions": users,
                "trial": "held"}

    def _held_check(self, state: RunState, users: list, new: tuple, one: Targets,
                    costs: torch.Tensor) -> tuple:
        """(the motions simulated, their (scores, success)) for a held trial of ``users``
        (their targets ``one``): ``new`` (basis, their weights) the model without the
        field; all in one check, or with ``solver.reduce.chunk`` c > 0, c at a time, those
        whose torque cost rose most (``costs``: theirs on ``new``, over their reference's)
        first, until a chunk holds a motion worse than its reference: the trial is then
        refused, as it would be had every user been simulated."""
        c, (basis, weights) = self.cfg.solver.reduce.chunk, new
        if not c:
            return users, self._check(basis, weights, one, until_failure=True)
        rise = costs / torch.tensor([state.reference["cost"][j] for j in users]).clamp_min(1e-300)
        order = torch.argsort(rise, descending=True, stable=True).tolist()
        done, parts = [], []
        for lo in range(0, len(order), c):
            part = order[lo:lo + c]
            scores, ok = self._check(basis, weights.select_motions(part), one.select(part),
                                     until_failure=True)
            done, parts = done + [users[i] for i in part], parts + [scores]
            if not self._no_worse(state, [users[i] for i in part], scores, ok):
                break
        scores = Scores.join(parts)
        return done, (scores, scores.succeeded(self.cfg.success.rmse, self.cfg.success.tip))

    @staticmethod
    def _no_worse(state: RunState, motions: list, scores: Scores, ok: list) -> bool:
        """:func:`no_worse` of ``motions``' scores against their references."""
        return no_worse({k: [state.reference[k][j] for j in motions] for k in ("rmse", "tip", "ok")},
                        scores, ok)

    def _trial(self, basis, weights, tg: Targets, state: RunState, victim: int) -> dict:
        """The basis without field ``victim``, refitted by EM (its EM steps counted, to
        be logged when the trial is applied)."""
        _, keep, nb, nw, support = self._without(basis, weights, state, victim, tg)
        self.log.busy(M=basis.M, trying=victim)
        steps = SimpleNamespace(step=0)          # _em ticks it; the run's step when applied
        cost = self._em(nb, nw, tg, steps, support=support)[-1]
        return {"victim": victim, "keep": keep, "model": (nb, nw), "support": support,
                "cost": cost, "em_steps": steps.step, "motions": list(range(tg.N)), "trial": "refit"}

    def _without(self, basis, weights, state: RunState, victim: int, tg: Targets) -> tuple:
        """(its position, the positions kept, basis, weights, support) once field
        ``victim`` is gone; a motion that lost it may use any field left, or with
        ``solver.reduce.reach`` its own and those in reach (:meth:`_reach`)."""
        pos = state.ids.index(victim)
        keep = [i for i in range(basis.M) if i != pos]
        nb = basis.select(keep)
        support = None if state.support is None else [[row[i] for i in keep] for row in state.support]
        for j, row in enumerate(state.support or []):
            if row[pos]:
                support[j] = self._reach(nb, tg, j, support[j])
        return pos, keep, nb, weights.select_fields(keep), support

    def _reach(self, basis, tg: Targets, j: int, own: list) -> list:
        """The fields motion j may draw on once it has lost one: every field of ``basis``,
        or with ``solver.reduce.reach`` r > 0 its ``own`` (bools) and those whose Gaussian
        reaches r at one of its samples at least."""
        r = self.cfg.solver.reduce.reach
        if not r:
            return [True] * basis.M
        near = (basis.gaussians(tg.q[j][tg.mask[j]]) >= r).any(0).tolist()
        return [a or b for a, b in zip(own, near)]

    def _checks(self, models: list, tg: Targets) -> list:
        """(scores, success) of each model, for a trial's judge (:meth:`_accepts`, which
        refuses any failed simulation): one batch for several, else :meth:`_check` up to
        the first failure."""
        if len(models) == 1:
            return [self._check(*models[0], tg, until_failure=True)]
        return [(s, s.succeeded(self.cfg.success.rmse, self.cfg.success.tip))
                for s in score_models(self.body, models, tg, self.options)]

    def _efolds(self, basis, weights, tg: Targets) -> list:
        """Each motion's e-folds of local error growth along its path (:mod:`.fit.stability`)."""
        return stability.growth(self.body, basis, weights, tg).efolds.tolist()

    def _accepts(self, state: RunState, trial: dict, tg: Targets) -> bool:
        """Whether a trial's check keeps every motion it simulated (``trial["motions"]``)
        no worse than the reference and, with ``solver.reduce.growth``, adds no more than
        that many e-folds of error growth to any of them (``trial["efolds"]``, computed
        once); a ``refused`` trial is not; one without a check (a fixed M, or a field no
        motion used) is."""
        if trial.get("refused"):
            return False
        if trial["check"] is None:
            return True
        motions = trial["motions"]
        if not self._no_worse(state, motions, *trial["check"]):
            return False
        allow = self.cfg.solver.reduce.growth
        if allow is None:
            return True
        if "efolds" not in trial:
            nb, nw = trial["model"]
            trial["efolds"] = self._efolds(nb, nw.select_motions(motions), tg.select(motions))
        return all(e <= state.reference["efolds"][j] + allow for j, e in zip(motions, trial["efolds"]))

    def _apply_trial(self, state: RunState, trial: dict, tg: Targets, total) -> bool:
        """Decide a trial, log it, record it and save; whether the field was removed."""
        state.step += trial["em_steps"]
        state.cursor += 1
        accept = self._accepts(state, trial, tg)
        cost, victim, check = trial["cost"], trial["victim"], trial["check"]
        step = self._tick(state)
        if cost is not None:                         # a field kept without a trial has none
            self.log.scalar("torque_cost/reduce", cost, step)
        self.log.scalar("reduce/removed", float(accept), step)
        if accept:
            nb, nw = trial["model"]
            state.model = model_state(nb, nw)
            state.ids = [state.ids[i] for i in trial["keep"]]
            state.support = trial["support"]
            costs = trial.get("costs")                 # a refitted trial changes every motion's
            state.reference["cost"] = costs if costs is not None else torque.torque_costs(nb, nw, tg).tolist()
            self.log.model(nb, nw, step)
            if check is not None:
                scores, ok = check
                new = (("rmse", scores.rmse), ("tip", scores.tip), ("ok", ok),
                       ("efolds", trial.get("efolds")))
                for i, j in enumerate(trial["motions"]):
                    for key, x in new:
                        if x is not None:
                            state.reference[key][j] = x[i]
                self.log.scores(scores, tg.select(trial["motions"]), step,
                                overview=len(trial["motions"]) == tg.N)
            else:
                self.log.scalar("0_overview/torque_cost", cost, step)
        refused = {"refused": trial["refused"]} if trial.get("refused") else {}
        self.log.status(total=total(len(state.ids)), M=len(state.ids), field=victim,
                        removed=bool(accept), trial=trial["trial"], **(refused or {"cost": cost}))
        state.history.setdefault("reduce", []).append(
            {"field": victim, "removed": bool(accept), "trial": trial["trial"], "M_after": len(state.ids),
             **refused})
        self.save(state)
        return accept

    def _path(self, state: RunState, tg: Targets):
        p = self.cfg.solver.path
        basis, weights = model_from_state(state.model)
        self.log.stage("path", p.steps, state.cursor)
        if state.path is None:               # the model after reduce: logged with its figures
            scores, ok = self._check(basis, weights, tg)
            self.log.scores(scores, tg, self._tick(state), figures=True)
            shoot = not all(ok) and self.cfg.solver.shooting.iterations
            if shoot:
                self._shoot(basis, weights, tg, [j for j, x in enumerate(ok) if not x], state)
                scores, ok = self._check(basis, weights, tg)
                self.log.scores(scores, tg, self._tick(state))
                state.model = model_state(basis, weights)
            state.path = {"needed": not all(ok), "lr": p.lr, "optimizer": None, "best": None,
                          "motions": ([j for j, x in enumerate(ok) if not x]
                                      if p.motions == "unreproduced" else None)}
            if not state.path["needed"]:
                self.log.status(advance=0, total=0, skipped="every motion reproduced")
            if shoot:                        # its own unit: a resumed run does not shoot again
                self.save(state)
        if not state.path["needed"] or state.cursor >= p.steps:
            self.log.end_stage()
            return self._advance(state)
        self.log.busy(step=state.cursor + 1)
        res = path_fit.path_step(self.body, basis, weights, tg, lr=state.path["lr"],
                                 best=state.path["best"], optimizer_state=state.path["optimizer"],
                                 velocity_weight=p.velocity_weight,
                                 phases=self.cfg.model.phases == "variable", options=self.options,
                                 fields=state.path.get("motions") is None,
                                 motions=state.path.get("motions"), distributed=True)
        if res.best is None:                 # the simulation fails at the starting point
            state.history["path"] = res.failure
            self.log.status(advance=0, failed="the simulation fails at the start")
            self.log.end_stage()
            return self._advance(state)
        state.path.update(lr=res.lr, best=res.best, optimizer=res.optimizer)
        state.model = model_state(basis, weights)
        step = self._tick(state)
        self.log.scalar("path/loss", res.loss, step)
        self.log.scalar("path/lr", res.lr, step)
        self.log.model(basis, weights, step)
        self.log.status(loss=res.loss, lr=res.lr)
        state.cursor += 1
        self.save(state)

    def _shoot(self, basis, weights, tg: Targets, motions: list, state: RunState, opts=None) -> None:
        """Multiple-shooting path matching of ``motions``' weights, the basis fixed
        (:func:`tflearn.fit.shooting.shooting_match`; ``opts``, by default
        ``solver.shooting``'s), the motions shared by the ranks; ``weights`` changed in place."""
        opts = opts or self.cfg.solver.shooting.options(self.cfg.model.phases == "variable")
        keys = shooting.keys_of(opts)
        mine = [motions[i] for i in parallel.mine(len(motions))]
        self.log.busy(shooting=len(motions))
        rows = []
        if mine:
            res = shooting.shooting_match(self.body, basis, weights, tg, options=opts, sim=self.options,
                                          motions=mine)
            rows = [{"theta": x.tolist(), "loss": loss if loss < float("inf") else None,
                     "failure": res.failures.get(tg.names[j])}
                    for j, x, loss in zip(mine, weights.flat(keys)[mine], res.loss)]
        rows = parallel.gather_motions(len(motions), rows)
        weights.set_flat(keys, torch.tensor([r["theta"] for r in rows], dtype=torch.float64), motions)
        state.history["shooting"] = {tg.names[j]: {k: r[k] for k in ("loss", "failure")}
                                     for j, r in zip(motions, rows)}

    def _adopt(self, state: RunState, tg: Targets, stage: str, basis, weights, cost: float, **extra):
        """Make a stage's model the run's: scored by simulation, logged, and recorded in
        the history under ``stage`` (M, ``extra``, its torque cost, success); returns
        (scores, success per motion)."""
        scores, ok = self._check(basis, weights, tg)
        step = self._tick(state)
        self.log.scalar(f"torque_cost/{stage}", cost, step)
        self.log.scores(scores, tg, step, figures=True)
        self.log.model(basis, weights, step)
        state.model = model_state(basis, weights)
        state.history[stage] = {"M": basis.M, **extra, "torque_cost": cost, "success": ok}
        return scores, ok

    def _layout(self, state: RunState, tg: Targets):
        """The spanning basis (:func:`tflearn.fit.layout.spanning_basis`), each motion's
        weights on its P windows by NNLS, the model scored by simulation."""
        self.log.stage("layout", 1)
        basis, weights = layout_model(self.cfg, self.body, tg)
        cost = float(torque.solve_weights(basis, weights, tg, ridge=self.cfg.solver.ridge).sum())
        _, ok = self._adopt(state, tg, "layout", basis, weights, cost)
        self.log.status(M=basis.M, cost=cost, reproduced=f"{sum(ok)}/{tg.N}")
        self.log.end_stage()
        self._advance(state)
        self.save(state)

    def _rescue(self, state: RunState, tg: Targets):
        """(``solver.rescue.enabled``) Rounds (at most ``solver.rescue.rounds``; one unit
        each) of :meth:`_rescue_round` on the motions the run's result (:meth:`final_model`)
        still does not reproduce, until every motion is reproduced, a round improves none,
        or the motions left are the last round's (a layout depends on its motions alone);
        each round is recorded in ``history.rescue`` (a list)."""
        rounds = self.cfg.solver.rescue.rounds
        while state.cursor < rounds:
            basis, weights = self.final_model(state)
            scores, ok = self._check(basis, weights, tg)
            last = state.history.get("rescue", [{}])[-1].get("motions")
            if all(ok) or last == [n for n, x in zip(tg.names, ok) if not x]:
                break                   # (the last round's motions: its fields laid out again)
            self.log.stage("rescue", rounds, state.cursor)
            record = self._rescue_round(state, tg, basis, weights, scores, ok)
            state.history.setdefault("rescue", []).append(record)
            state.cursor += 1
            self.log.status(M=record["M"], reproduced=f"{sum(ok) + len(record['reproduced'])}/{tg.N}",
                            kept=record["kept"])
            if not record["kept"]:
                break
            self.save(state)
        self.log.end_stage()
        self._advance(state)
        self.save(state)

    def _rescue_round(self, state: RunState, tg: Targets, basis, weights, scores: Scores,
                      ok: list) -> dict:
        """The motions that ``basis``, ``weights`` do not reproduce (``scores``, ``ok``) get
        fields laid out around them (:func:`tflearn.fit.layout.spanning_basis`,
        ``solver.rescue``'s layout) added to the basis; their weights start on the new
        fields alone, by NNLS (its ridge and torque weights), and multiple shooting
        (``solver.shooting``'s horizon, ``solver.rescue``'s iterations, tip and velocity
        weights) then fits them over the whole basis (with ``solver.shooting.used``, over
        the new fields their weights are on). A motion takes its new program where
        that reproduces it or, failing that, is simulated closer to it (joint RMSE); the
        others keep theirs, with zero weight on the new fields (their programs unchanged).
        The grown model becomes the run's result if some motion took its new program;
        returns the round's record."""
        r = self.cfg.solver.rescue
        todo = [j for j, x in enumerate(ok) if not x]
        sub = tg.select(todo)
        sub = replace(sub, coord_weight=inertia_weights(self.body, sub)
                      if r.torque_weight == "inertia" else None)
        laid = layout_basis(self.cfg, self.body, sub, r)
        grown, more = basis.extend(laid.eta, laid.K()), weights.extend_fields(laid.M)
        keys, subw = MotionWeights.PER_FIELD + MotionWeights.WINDOWS, more.select_motions(todo)
        new = _weight_support([[False] * basis.M + [True] * laid.M] * len(todo), subw.P)
        torque.solve_weights(grown, subw, sub, ridge=r.ridge, support=new)
        more.set_flat(keys, subw.flat(keys), todo)
        opts = replace(self.cfg.solver.shooting.options(self.cfg.model.phases == "variable"),
                       iterations=r.iterations, tip_weight=r.tip_weight,
                       velocity_weight=r.velocity_weight)
        self._shoot(grown, more, tg, todo, state, opts)
        after, now = self._check(grown, more, tg)
        took = [j for j in todo
                if now[j] or (after.failure[j] is None and after.rmse[j] < scores.rmse[j])]
        back = [j for j in todo if j not in took]
        if back:
            more.set_flat(keys, weights.extend_fields(laid.M).flat(keys)[back], back)
        if took:                              # the run's result from here (not path's best)
            state.model, state.path["best"] = model_state(grown, more), None
        return {"motions": [tg.names[j] for j in todo], "added": laid.M,
                "M": grown.M if took else basis.M,
                "reproduced": [tg.names[j] for j in todo if now[j]],
                "improved": [tg.names[j] for j in took], "kept": bool(took)}

    def _slsqp(self, state: RunState, tg: Targets):
        gen = self._gen(state)
        self.log.stage("slsqp", self.cfg.solver.slsqp.max_iter)
        M, n = self.cfg.model.fields, tg.q.shape[-1]
        flat = tg.q[tg.mask]
        eta = flat[torch.randint(len(flat), (M,), generator=gen, device="cpu")]
        basis = FieldBasis(eta, torch.eye(n, dtype=torch.float64).expand(M, n, n).clone(), kind="diag")
        weights = MotionWeights.zeros(M, tg.duration, tg.names)
        torque.solve_weights(basis, weights, tg)

        def cb(nit, cost):
            self.log.scalar("torque_cost/slsqp", cost, self._tick(state))
            self.log.status(cost=cost)
        res = slsqp.fit_slsqp(basis, weights, tg, max_iter=self.cfg.solver.slsqp.max_iter, callback=cb)
        self.log.end_stage()
        self.log.model(res["basis"], res["weights"], self._tick(state))
        state.model = model_state(res["basis"], res["weights"])
        state.history["slsqp"] = {k: res[k] for k in ("initial_cost", "cost", "nit", "nfev",
                                                       "message", "wall_time")}
        state.rng = gen.get_state()
        self._advance(state)
        self.save(state)

    # ---- artefacts
    def final_model(self, state: RunState):
        """The run's result: the current model, or path matching's best point."""
        best = (state.path or {}).get("best")
        return model_from_state(best["model"] if best is not None else state.model)

    def finish(self, state: RunState, tg: Targets) -> dict:
        basis, weights = self.final_model(state)
        scores, ok = self._check(basis, weights, tg)
        step = self._tick(state)
        self.log.scores(scores, tg, step, figures=True)
        self.log.model(basis, weights, step)
        lb = basis_io.LearnedBasis(self.body, basis, weights, tg.q0, tg.qd0, tg.rate)
        metrics = summarize(scores, ok, tg, basis.M, state.elapsed + time.time() - self._t0,
                            stability.growth(self.body, basis, weights, tg))
        for name, eps in zip(tg.names, self.resolution):
            metrics["motions"][name]["torque_resolution"] = eps
        metrics["overall"]["simulations"] = state.simulations + sim_mod.calls - self._calls0
        metrics["history"] = state.history
        state.stage = "done"
        if parallel.rank() == 0:
            self._write(state, tg, scores, lb, metrics)
        return metrics

    def _write(self, state: RunState, tg: Targets, scores: Scores, lb, metrics: dict) -> None:
        """The artefacts of a finished run (rank 0)."""
        write_figures(self.body, tg, scores, self.out, self.cfg.log.figures)
        config_mod.dump(self.cfg, self.out / "config.yaml")
        write_text(self.out / "metrics.json", json.dumps(metrics, indent=1))
        basis_io.save(lb, self.out / "basis.json")
        self.log.hparams({"seed": self.cfg.seed, "method": self.cfg.solver.method,
                          "stiffness": self.cfg.model.stiffness, "phases": self.cfg.model.phases,
                          "fields": self.cfg.model.fields, "data": str(self.cfg.data)}, metrics)
        self._write_checkpoint(state)


def write_figures(body, tg: Targets, scores: Scores, out: Path, count: Optional[int] = None) -> None:
    """OUT/figures/NAME.png: the target and simulated paths of the ``count`` motions
    furthest from their paths (None: every motion)."""
    from .plots import figures as plots
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    for j in scores.worst(count):
        name, k = tg.names[j], int(tg.mask[j].sum())
        plots.save(plots.motion_sheet(body, tg.t[j, :k], {"target": tg.q[j, :k],
                                                          "simulated": scores.q_sim[j, :k]},
                                      title=f"{name}: rmse {scores.rmse[j]:.4f} rad, "
                                            f"tip {100 * scores.tip[j]:.2f} cm"),
                   fig_dir / f"{name}.png")


def config_changes(old: dict, new: dict, prefix: str = "") -> list:
    """The dotted keys whose values differ between two dumped configs (sections compared
    key by key; a key only one of them has counts as differing)."""
    out = []
    for key in sorted(old.keys() | new.keys()):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict) and key != "body":
            out += config_changes(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key}")
    return out


def run_device(name: str) -> torch.device:
    """The device a run's config names, checked to be on this machine (ConfigError naming
    it otherwise); plain ``cuda`` is this process' GPU (:func:`tflearn.parallel.local`)."""
    device = parallel.local(name)
    if device.type != "cuda":
        return device
    if not torch.cuda.is_available():
        raise ConfigError(f"device {name!r}: this machine has no CUDA device that torch "
                          f"{torch.__version__} can use; set device: cpu")
    if device.index >= torch.cuda.device_count():
        raise ConfigError(f"device {name!r}: this machine has {torch.cuda.device_count()} CUDA "
                          f"device(s), numbered from 0")
    return device


def on_device(device: torch.device):
    """``with on_device(d):`` tensors made without a device are made on ``d`` (torch's
    default device); on the CPU nothing changes."""
    return contextlib.nullcontext() if device.type == "cpu" else device


def _same_check(a: tuple, b: tuple) -> bool:
    """Whether two :meth:`Run._check` keys (targets, model state, flags) are the same:
    the same targets object, equal tensors and equal values."""
    def same(x, y):
        if isinstance(x, dict):
            return x.keys() == y.keys() and all(same(x[k], y[k]) for k in x)
        if isinstance(x, torch.Tensor):
            return x.shape == y.shape and bool(torch.equal(x, y))
        return x == y
    return a[0] is b[0] and a[2:] == b[2:] and same(a[1], b[1])


def empty_basis(cfg: Config, body) -> FieldBasis:
    """An empty basis of the config's stiffness kind and field damping on the body's blocks."""
    m = cfg.model
    return FieldBasis.empty(body.nv, m.stiffness, body.blocks, m.field_damping)


def layout_basis(cfg: Config, body, tg: Targets, c=None) -> FieldBasis:
    """The spanning basis (:func:`tflearn.fit.layout.spanning_basis`) of ``c``'s shape,
    radius and stiffness (by default ``solver.layout``) around the motions of ``tg``."""
    c = c or cfg.solver.layout
    return layout.spanning_basis(body, tg, empty_basis(cfg, body), c.radius, c.stiffness, c.shape)


def layout_model(cfg: Config, body, tg: Targets) -> tuple:
    """The ``layout`` stage's model before NNLS: :func:`layout_basis` and zero weights on
    each motion's ``model.windows`` sub-movement windows."""
    basis = layout_basis(cfg, body, tg)
    return basis, MotionWeights.zeros(basis.M, tg.duration, tg.names,
                                      submovement_windows(tg, cfg.model.windows))


def run(cfg: Config, restart: bool = False, stop_after: int | None = None,
        progress: bool | None = None) -> dict:
    """Train with a validated config (:class:`tflearn.config.Config`); returns metrics.json's dict."""
    return Run(cfg, stop_after=stop_after, progress=progress).execute(restart=restart)
