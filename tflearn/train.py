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
                over all of them (so no motion fits worse than alone); fields that
                nearly coincide (``solver.merge``) merged and refined jointly by EM;
3. ``reduce`` — backward elimination: drop each field in turn (smallest share first)
                and keep it dropped if no motion gets worse by simulation
                (:func:`no_worse`) — the smallest M found is reported (one unit per
                field tried);
4. ``path``   — path matching through ``odeint`` for motions not yet reproduced
                (safeguarded Adam on the simulated path loss; one unit per step);
5. ``done``   — ``basis.json``, ``metrics.json``, ``config.yaml``, figures, TensorBoard.

With ``solver.method: slsqp`` the single stage ``slsqp`` replaces 1–4: the thesis'
baseline (:func:`tflearn.fit.slsqp.fit_slsqp`, torque matching only) with
``model.fields`` diagonal-stiffness fields from a seeded random guess — centres at
postures drawn from the motions' samples, K = I, weights by NNLS.

The run's state is a :class:`RunState`; checkpoints hold it as plain tensors and JSON
values only (loaded with ``torch.load(weights_only=True)``).
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

import torch

from . import config as config_mod
from .body import from_config
from .config import Config, ConfigError
from .data import check_resolution, load_motions
from .errors import InputError
from .fields import FieldBasis, MotionWeights, model_from_state, model_state
from .fit import path as path_fit
from .fit import search, slsqp, torque
from .fit.targets import Targets, prepare
from .io import basis as basis_io
from .io.files import replacing, write_text
from .metrics import Scores, score, summarize

CHECKPOINT_FORMAT = "tflearn-checkpoint/2"
SEQUENCES = {"pipeline": ("each", "pool", "reduce", "path", "done"),
             "slsqp": ("slsqp", "done")}


class Interrupted(Exception):
    """Raised by :func:`run` after ``stop_after`` checkpoints (used to test resuming)."""


class CheckpointError(InputError):
    """A checkpoint that cannot be resumed; the message names the file and the problem."""


@dataclass
class RunState:
    """Everything a run needs to resume: where it is (stage, cursor within the stage),
    the random generator, the per-motion fits of ``each``, the current model
    (:func:`~tflearn.fields.model_state`), the reference scores of ``reduce`` and
    its elimination order, path matching's optimizer and best point, the history
    reported in metrics.json, and the compute time spent so far."""

    config: dict
    stage: str
    rng: torch.Tensor
    cursor: int = 0
    step: int = 0
    elapsed: float = 0.0
    fits: list = field(default_factory=list)          # [(η (M_j×n), K (M_j×n×n))]
    model: Optional[dict] = None
    history: dict = field(default_factory=dict)
    reference: Optional[dict] = None                   # {"rmse", "tip", "ok"} per motion
    order: Optional[list] = None                       # reduce: fields by share
    ids: Optional[list] = None                         # reduce: original ids kept
    path: Optional[dict] = None                        # {"needed", "lr", "optimizer", "best"}

    def to_dict(self) -> dict:
        return {"format": CHECKPOINT_FORMAT, **asdict(self)}

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
    return {"rmse": scores.rmse, "tip": scores.tip, "ok": ok}


# ------------------------------------------------------------------------------ the run

class Run:
    """One training run: owns the config, the data, the logger and the checkpoint."""

    def __init__(self, cfg: Config, stop_after: int | None = None, progress: bool | None = None):
        self.cfg = cfg
        self.out = Path(cfg.out)
        try:
            self.body = from_config(cfg.body)
        except ValueError as err:
            raise ConfigError(f"config key 'body': {err}") from None
        self.options = cfg.solver.path.options()
        self.stop_after = stop_after
        self.checkpoints = 0
        self.progress = cfg.log.progress if progress is None else progress
        self.ckpt_path = self.out / "checkpoint.pt"
        self.writer = None
        self.bar = None
        self.stages = {"each": self._each, "pool": self._pool, "reduce": self._reduce,
                       "path": self._path, "slsqp": self._slsqp}
        self.sequence = SEQUENCES[cfg.solver.method]
        if cfg.solver.method == "slsqp":
            m = cfg.model
            if m.fields < 1 or m.stiffness != "diag" or m.phases != "fixed":
                raise ConfigError(
                    "solver.method 'slsqp' (the thesis' baseline) fits a basis of a given size "
                    "with diagonal stiffness and fixed phases: it needs model.fields ≥ 1, "
                    f"model.stiffness=diag and model.phases=fixed (got {m.fields}, "
                    f"{m.stiffness!r}, {m.phases!r})")

    # ---- logging
    def _open_logs(self):
        if self.cfg.log.tensorboard:
            from torch.utils.tensorboard import SummaryWriter
            self.writer = SummaryWriter(str(self.out / "tensorboard"))
        if self.progress:
            from tqdm import tqdm
            self.bar = tqdm(total=None, unit="unit", dynamic_ncols=True)

    def scalar(self, tag, value, step):
        if self.writer:
            self.writer.add_scalar(tag, float(value), step)

    def status(self, stage, **values):
        if self.bar is not None:
            self.bar.set_description(stage)
            self.bar.set_postfix({k: f"{v:.3g}" for k, v in values.items()})
            self.bar.update(1)

    def log_model(self, basis, weights, step):
        if not self.writer or basis.M == 0:
            return
        self.writer.add_histogram("weights/a", weights.a.detach(), step)
        self.writer.add_histogram("weights/b", weights.b.detach(), step)
        self.writer.add_histogram("stiffness/eigenvalues",
                                  torch.linalg.eigvalsh(basis.K().detach()).flatten(), step)
        self.scalar("model/M", basis.M, step)

    def log_scores(self, scores: Scores, tg: Targets, step, figures: bool = False):
        for j, name in enumerate(tg.names):
            self.scalar(f"rmse/{name}", scores.rmse[j], step)
            self.scalar(f"tip/{name}", scores.tip[j], step)
            self.scalar(f"torque_error/{name}", scores.torque[j], step)
        if figures and self.writer:
            from . import plots
            for j, name in enumerate(tg.names):
                k = int(tg.mask[j].sum())
                fig = plots.motion_sheet(self.body, tg.t[j, :k],
                                         {"target": tg.q[j, :k], "simulated": scores.q_sim[j, :k]},
                                         title=name)
                self.writer.add_figure(f"paths/{name}", fig, step)

    # ---- checkpoints
    def save(self, state: RunState):
        state.elapsed += time.time() - self._t0
        self._t0 = time.time()
        with replacing(self.ckpt_path) as tmp:
            torch.save(state.to_dict(), tmp)
        self.checkpoints += 1
        if self.stop_after is not None and self.checkpoints >= self.stop_after:
            raise Interrupted(f"stopped after {self.checkpoints} checkpoints")

    def load(self) -> Optional[RunState]:
        if not self.ckpt_path.exists():
            return None
        try:
            doc = torch.load(self.ckpt_path, weights_only=True)
        except Exception as err:
            raise CheckpointError(f"{self.ckpt_path}: not a readable checkpoint "
                                  f"({type(err).__name__}); pass --restart to start afresh") from None
        state = RunState.from_dict(doc, str(self.ckpt_path))
        if state.config != self.cfg.model_dump():
            raise CheckpointError(
                f"{self.ckpt_path}: a checkpoint of a different config is in this output folder; "
                f"choose another out= or pass --restart")
        return state

    # ---- stages
    def execute(self, restart: bool = False) -> dict:
        torch.manual_seed(self.cfg.seed)
        self._t0 = time.time()
        motions = load_motions(self.cfg.data, self.body, strict=self.cfg.strict)
        self.resolution = check_resolution(self.body, motions)
        tg = prepare(self.body, motions)
        self.out.mkdir(parents=True, exist_ok=True)
        if restart:
            self.ckpt_path.unlink(missing_ok=True)
        state = self.load()
        if state is None:
            gen = torch.Generator().manual_seed(self.cfg.seed)
            state = RunState(config=self.cfg.model_dump(), stage=self.sequence[0], rng=gen.get_state())
        elif self.progress:
            print(f"resuming {self.out} at stage {state.stage} ({state.cursor})")
        self._open_logs()
        try:
            while state.stage != "done":
                self.stages[state.stage](state, tg)
            return self.finish(state, tg)
        finally:
            if self.writer:
                self.writer.close()
            if self.bar is not None:
                self.bar.close()

    def _gen(self, state: RunState) -> torch.Generator:
        gen = torch.Generator()
        gen.set_state(state.rng)
        return gen

    def _advance(self, state: RunState):
        state.stage = self.sequence[self.sequence.index(state.stage) + 1]
        state.cursor = 0

    def _check(self, basis, weights, tg: Targets, state: RunState, figures=False):
        scores = score(self.body, basis, weights, tg, self.options)
        self.log_scores(scores, tg, state.step, figures)
        return scores, scores.succeeded(self.cfg.success.rmse, self.cfg.success.tip)

    def _em(self, basis, weights, tg, state: RunState):
        c = self.cfg.solver.em

        def cb(step, costs):
            state.step += 1
            self.scalar("torque/cost_total", costs.sum(), state.step)
        return torque.em(basis, weights, tg, steps=c.steps, tol=c.tol,
                         phases=self.cfg.model.phases == "variable", callback=cb)

    def _each(self, state: RunState, tg: Targets):
        c, m = self.cfg.solver, self.cfg.model
        j = state.cursor
        if j >= tg.N:
            return self._advance(state)
        gen = self._gen(state)
        one = tg.select([j])
        b, w, costs = search.grow(one, m.stiffness, self.body.blocks, c.each.max_fields, c.each.tol,
                                  c.init.candidates, c.init.stiffness_grid, gen, c.em.steps,
                                  phases=m.phases == "variable", em_tol=c.em.tol,
                                  reproduced=lambda b, w: all(self._check(b, w, one, state)[1]))
        state.fits.append((b.eta.detach().clone(), b.K().detach().clone()))
        state.rng = gen.get_state()
        state.step += 1
        self.scalar(f"each/torque_cost/{tg.names[j]}", costs[0], state.step)
        self.scalar(f"each/fields/{tg.names[j]}", b.M, state.step)
        self.status("each", motion=j, M=b.M, cost=float(costs[0]))
        state.cursor = j + 1
        self.save(state)

    def _pool(self, state: RunState, tg: Targets):
        merge = self.cfg.solver.merge
        basis, weights = search.pool(tg, state.fits, self.cfg.model.stiffness, self.body.blocks)
        basis, weights, merged = search.merge_close(basis, weights, merge.distance, merge.stiffness)
        if merged or self.cfg.model.phases == "variable":   # pooled phases start at default
            self._em(basis, weights, tg, state)
        cost = float(torque.solve_weights(basis, weights, tg).sum())
        scores, ok = self._check(basis, weights, tg, state, figures=True)
        self.log_model(basis, weights, state.step)
        state.model = model_state(basis, weights)
        state.history["pool"] = {"M": basis.M, "merged": merged, "torque_cost": cost, "success": ok}
        state.reference = _reference(scores, ok)
        self.status("pool", M=basis.M, cost=cost, ok=sum(ok))
        self._advance(state)
        self.save(state)

    def _reduce(self, state: RunState, tg: Targets):
        """Backward elimination. With model.fields = 0 a field goes only if no motion gets
        worse (:func:`no_worse`); with model.fields = M the smallest-share fields go
        until M remain."""
        fixed = self.cfg.model.fields
        basis, weights = model_from_state(state.model)
        if state.order is None:
            shares = search.field_shares(basis, weights, tg)
            state.order = [int(i) for i in torch.argsort(shares)]
            state.ids = list(range(basis.M))
        k = state.cursor
        if basis.M <= max(fixed, 1) or k >= len(state.order):
            return self._advance(state)
        victim = state.order[k]
        state.cursor = k + 1
        pos = state.ids.index(victim)
        keep = [i for i in range(basis.M) if i != pos]
        nb, nw = basis.select(keep), weights.select_fields(keep)
        self._em(nb, nw, tg, state)
        accept = True
        if not fixed:
            scores, ok = self._check(nb, nw, tg, state)
            accept = no_worse(state.reference, scores, ok)
        if accept:
            state.model = model_state(nb, nw)
            state.ids = [state.ids[i] for i in keep]
            if not fixed:
                state.reference = _reference(scores, ok)
        self.status("reduce", M=len(state.ids), removed=float(accept))
        state.history.setdefault("reduce", []).append(
            {"field": victim, "removed": bool(accept), "M_after": len(state.ids)})
        self.save(state)

    def _path(self, state: RunState, tg: Targets):
        p = self.cfg.solver.path
        basis, weights = model_from_state(state.model)
        if state.cursor == 0:
            _, ok = self._check(basis, weights, tg, state)
            state.path = {"needed": not all(ok), "lr": p.lr, "optimizer": None, "best": None}
        if not state.path["needed"] or state.cursor >= p.steps:
            return self._advance(state)
        res = path_fit.path_step(self.body, basis, weights, tg, lr=state.path["lr"],
                                 best=state.path["best"], optimizer_state=state.path["optimizer"],
                                 velocity_weight=p.velocity_weight,
                                 phases=self.cfg.model.phases == "variable", options=self.options)
        if res.best is None:                 # the simulation fails at the starting point
            state.history["path"] = res.failure
            self.status("path", failed=1.0)
            return self._advance(state)
        state.path.update(lr=res.lr, best=res.best, optimizer=res.optimizer)
        state.model = model_state(basis, weights)
        state.step += 1
        self.scalar("path/loss", res.loss, state.step)
        self.status("path", loss=res.loss, lr=res.lr)
        state.cursor += 1
        self.save(state)

    def _slsqp(self, state: RunState, tg: Targets):
        gen = self._gen(state)
        M, n = self.cfg.model.fields, tg.q.shape[-1]
        flat = tg.q[tg.mask]
        eta = flat[torch.randint(len(flat), (M,), generator=gen)]
        basis = FieldBasis(eta, torch.eye(n, dtype=torch.float64).expand(M, n, n).clone(), kind="diag")
        weights = MotionWeights.zeros(M, tg.duration, tg.names)
        torque.solve_weights(basis, weights, tg)

        def cb(nit, cost):
            state.step += 1
            self.scalar("torque/cost_total", cost, state.step)
            self.status("slsqp", iteration=nit, cost=cost)
        res = slsqp.fit_slsqp(basis, weights, tg, max_iter=self.cfg.solver.slsqp.max_iter, callback=cb)
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
        scores, ok = self._check(basis, weights, tg, state, figures=True)
        lb = basis_io.LearnedBasis(self.body, basis, weights, tg.q0, tg.qd0, tg.rate)
        metrics = summarize(scores, ok, tg, basis.M, state.elapsed + time.time() - self._t0)
        for name, eps in zip(tg.names, self.resolution):
            metrics["motions"][name]["torque_resolution"] = eps
        metrics["history"] = state.history
        write_figures(self.body, tg, scores, self.out)
        config_mod.dump(self.cfg, self.out / "config.yaml")
        write_text(self.out / "metrics.json", json.dumps(metrics, indent=1))
        basis_io.save(lb, self.out / "basis.json")
        if self.writer:
            hp = {"seed": self.cfg.seed, "stiffness": self.cfg.model.stiffness,
                  "phases": self.cfg.model.phases, "data": str(self.cfg.data)}
            self.writer.add_hparams(hp, {"hparam/M": basis.M,
                                         "hparam/rmse": metrics["overall"]["rmse"],
                                         "hparam/tip": metrics["overall"]["tip"],
                                         "hparam/success": float(all(ok))})
        state.stage = "done"
        with replacing(self.ckpt_path) as tmp:
            torch.save(state.to_dict(), tmp)
        return metrics


def write_figures(body, tg: Targets, scores: Scores, out: Path) -> None:
    from . import plots
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    for j, name in enumerate(tg.names):
        k = int(tg.mask[j].sum())
        plots.save(plots.motion_sheet(body, tg.t[j, :k], {"target": tg.q[j, :k],
                                                          "simulated": scores.q_sim[j, :k]},
                                      title=f"{name}: rmse {scores.rmse[j]:.4f} rad, "
                                            f"tip {100 * scores.tip[j]:.2f} cm"),
                   fig_dir / f"{name}.png")


def run(cfg: Config, restart: bool = False, stop_after: int | None = None,
        progress: bool | None = None) -> dict:
    """Train with a validated config (:class:`tflearn.config.Config`); returns metrics.json's dict."""
    return Run(cfg, stop_after=stop_after, progress=progress).execute(restart=restart)
