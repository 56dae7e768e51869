"""The training pipeline behind ``train CONFIG``: motions → torques → fit → basis → metrics.

Stages, each checkpointed on completion of every unit of work so that an interrupted run
resumes where it stopped and ends with the same result:

1. ``each``   — every motion alone: greedy growth of its own fields from data-driven,
                seeded multi-start candidates, refined by EM, until its relative torque
                cost is below ``solver.each.tol`` and simulation reproduces it (one unit
                per motion);
2. ``pool``   — all per-motion fields in one basis, every motion's weights re-solved
                over all of them (so no motion fits worse than alone); fields closer than
                ``solver.merge.distance`` merged and refined jointly by EM;
3. ``reduce`` — backward elimination: drop each field in turn (smallest share first)
                and keep it dropped if no motion gets worse by simulation: every motion
                reproduced stays reproduced, and one not (yet) reproduced moves no
                further from its path (joint RMSE and tip error no larger) — the
                smallest M found is reported (one unit per field tried);
4. ``path``   — path matching through ``odeint`` for motions not yet reproduced
                (safeguarded Adam on the simulated path loss; one unit per step);
5. ``done``   — ``basis.json``, ``metrics.json``, figures, TensorBoard hparams.

With ``solver.method: slsqp`` the single stage ``slsqp`` replaces 1–4: the thesis'
baseline (:func:`tflearn.fit.slsqp.fit_slsqp`, torque matching only) with
``model.fields`` diagonal-stiffness fields from a seeded random guess — centres at
postures drawn from the motions' samples, K = I, weights by NNLS.
"""
from __future__ import annotations

import json
import time
import warnings
from pathlib import Path

import torch

from . import config as config_mod
from . import gestures as gestures_mod
from . import motion as motion_mod
from .body import from_config
from .fields import FieldBasis, MotionWeights
from .fit import path as path_fit
from .fit import search, slsqp, torque
from .fit.targets import Targets, prepare
from .io import basis as basis_io

STAGES = ("each", "pool", "reduce", "path", "slsqp", "done")


class Interrupted(RuntimeError):
    """Raised by :func:`run` after ``stop_after`` checkpoints (used to test resuming)."""


def load_motions(data, body) -> list:
    """Motions named by a config's ``data``: "gestures", a folder, or a list of files."""
    if data == "gestures":
        return [m for m, _ in gestures_mod.generate(body)]
    if isinstance(data, str):
        p = Path(data)
        if p.is_dir():
            return motion_mod.load_dir(p, body)
        return [motion_mod.load(p, body)]
    return [motion_mod.load(p, body) for p in data]


def check_resolution(body, motions) -> list:
    """Each motion's :func:`tflearn.motion.torque_resolution`; warns, naming the motion,
    for those above :data:`tflearn.motion.RESOLVED` (too fast for their sampling)."""
    eps = [motion_mod.torque_resolution(body, m) for m in motions]
    for m, e in zip(motions, eps):
        if e > motion_mod.RESOLVED:
            warnings.warn(f"motion {m.name!r}: its samples do not resolve it at {m.rate:.0f} Hz "
                          f"(spline torques an estimated {100 * e:.1f}% off, above "
                          f"{100 * motion_mod.RESOLVED:.0f}%); it may not be reproduced. "
                          f"Sample it faster or smooth it.", stacklevel=2)
    return eps


# ------------------------------------------------------------------ model (de)serialisation

def model_state(basis: FieldBasis, weights: MotionWeights) -> dict:
    return {"basis": {k: v.clone() for k, v in basis.state_dict().items()},
            "weights": {k: v.clone() for k, v in weights.state_dict().items()},
            "kind": basis.stiffness.kind, "blocks": basis.blocks, "names": weights.names}


def model_from_state(state: dict):
    eta = state["basis"]["eta"]
    M, n = eta.shape
    basis = FieldBasis(torch.zeros(M, n, dtype=torch.float64),
                       torch.eye(n, dtype=torch.float64).expand(M, n, n),
                       kind=state["kind"], blocks=state["blocks"])
    basis.load_state_dict(state["basis"])
    w = state["weights"]
    z = torch.zeros_like(w["a_raw"])
    weights = MotionWeights(z, z, w["duration"], names=state["names"])
    weights.load_state_dict(w)
    return basis, weights


# ------------------------------------------------------------------------------ the run

class Run:
    """One training run: owns the config, the data, the logger and the checkpoint."""

    def __init__(self, cfg: dict, stop_after: int | None = None, progress: bool | None = None):
        self.cfg = cfg
        self.out = Path(cfg["out"])
        self.body = from_config(cfg["body"])
        self.stop_after = stop_after
        self.checkpoints = 0
        self.progress = cfg["log"]["progress"] if progress is None else progress
        self.ckpt_path = self.out / "checkpoint.pt"
        self.writer = None
        self.bar = None
        if cfg["solver"]["method"] == "slsqp":
            m = cfg["model"]
            if m["fields"] < 1 or m["stiffness"] != "diag" or m["phases"] != "fixed":
                raise config_mod.ConfigError(
                    "solver.method 'slsqp' (the thesis' baseline) fits a basis of a given size "
                    "with diagonal stiffness and fixed phases: it needs model.fields ≥ 1, "
                    f"model.stiffness=diag and model.phases=fixed (got {m['fields']}, "
                    f"{m['stiffness']!r}, {m['phases']!r})")

    # ---- logging
    def _open_logs(self):
        if self.cfg["log"]["tensorboard"]:
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

    def log_metrics(self, m, tg: Targets, step, figures: bool = False):
        for j, name in enumerate(tg.names):
            self.scalar(f"rmse/{name}", m["rmse"][j], step)
            self.scalar(f"tip/{name}", m["tip"][j], step)
            self.scalar(f"torque_error/{name}", m["torque"][j], step)
        if figures and self.writer:
            from . import plots
            for j, name in enumerate(tg.names):
                k = int(tg.mask[j].sum())
                fig = plots.motion_sheet(self.body, tg.t[j, :k],
                                         {"target": tg.q[j, :k], "simulated": m["q_sim"][j, :k]},
                                         title=name)
                self.writer.add_figure(f"paths/{name}", fig, step)

    # ---- checkpoints
    def save(self, state):
        state["elapsed"] = state.get("elapsed", 0.0) + (time.time() - self._t0)
        self._t0 = time.time()
        tmp = self.ckpt_path.with_suffix(".tmp")
        torch.save(state, tmp)
        tmp.replace(self.ckpt_path)
        self.checkpoints += 1
        if self.stop_after is not None and self.checkpoints >= self.stop_after:
            raise Interrupted(f"stopped after {self.checkpoints} checkpoints")

    def load(self):
        if not self.ckpt_path.exists():
            return None
        state = torch.load(self.ckpt_path, weights_only=False)
        if state.get("config") != self.cfg:
            raise config_mod.ConfigError(
                f"{self.ckpt_path}: a checkpoint of a different config is in this output folder; "
                f"choose another out= or pass --restart")
        return state

    # ---- stages
    def execute(self, restart: bool = False) -> dict:
        torch.manual_seed(self.cfg["seed"])
        self._t0 = time.time()
        motions = load_motions(self.cfg["data"], self.body)
        self.resolution = check_resolution(self.body, motions)
        tg = prepare(self.body, motions)
        self.out.mkdir(parents=True, exist_ok=True)
        if restart and self.ckpt_path.exists():
            self.ckpt_path.unlink()
        state = self.load()
        if state is None:
            gen = torch.Generator().manual_seed(self.cfg["seed"])
            first = "slsqp" if self.cfg["solver"]["method"] == "slsqp" else "each"
            state = {"config": self.cfg, "stage": first, "cursor": 0, "fits": [], "model": None,
                     "rng": gen.get_state(), "history": {}, "step": 0}
        elif self.progress:
            print(f"resuming {self.out} at stage {state['stage']} ({state['cursor']})")
        self._open_logs()
        try:
            while state["stage"] != "done":
                getattr(self, f"_stage_{state['stage']}")(state, tg)
            return self.finish(state, tg)
        finally:
            if self.writer:
                self.writer.close()
            if self.bar is not None:
                self.bar.close()

    def _gen(self, state):
        gen = torch.Generator()
        gen.set_state(state["rng"])
        return gen

    def _sim_kw(self):
        p = self.cfg["solver"]["path"]
        return {"method": p["method"], "rtol": p["rtol"], "atol": p["atol"], "max_evals": p["max_evals"]}

    def _advance(self, state, stage):
        state["stage"], state["cursor"] = stage, 0

    def _stage_each(self, state, tg):
        c, m = self.cfg["solver"], self.cfg["model"]
        j = state["cursor"]
        if j >= tg.N:
            return self._advance(state, "pool")
        gen = self._gen(state)
        one = tg.select([j])
        b, w, costs = search.grow(one, m["stiffness"], self.body.blocks,
                                  c["each"]["max_fields"], c["each"]["tol"],
                                  c["init"]["candidates"], c["init"]["stiffness_grid"], gen,
                                  c["em"]["steps"], phases=m["phases"] == "variable",
                                  em_tol=c["em"]["tol"],
                                  reproduced=lambda b, w: all(self._metrics(b, w, one, state)[1]))
        state["fits"].append((b.eta.detach().clone(), b.K().detach().clone()))
        state["rng"] = gen.get_state()
        state["step"] += 1
        self.scalar(f"each/torque_cost/{tg.names[j]}", costs[0], state["step"])
        self.scalar(f"each/fields/{tg.names[j]}", b.M, state["step"])
        self.status("each", motion=j, M=b.M, cost=float(costs[0]))
        state["cursor"] = j + 1
        self.save(state)

    def _em(self, basis, weights, tg, state, steps=None):
        c = self.cfg["solver"]["em"]

        def cb(step, costs):
            state["step"] += 1
            self.scalar("torque/cost_total", costs.sum(), state["step"])
        return torque.em(basis, weights, tg, steps=steps or c["steps"], tol=c["tol"],
                         phases=self.cfg["model"]["phases"] == "variable", callback=cb)

    def _metrics(self, basis, weights, tg, state, figures=False):
        m = path_fit.metrics(self.body, basis, weights, tg, **self._sim_kw())
        self.log_metrics(m, tg, state["step"], figures)
        ok = path_fit.succeeded(m, self.cfg["success"]["rmse"], self.cfg["success"]["tip"])
        return m, ok

    def _stage_pool(self, state, tg):
        kind, blocks = self.cfg["model"]["stiffness"], self.body.blocks
        basis, weights = search.pool(tg, state["fits"], kind, blocks)
        basis, weights, merged = search.merge_close(basis, weights, tg,
                                                    self.cfg["solver"]["merge"]["distance"])
        if merged or self.cfg["model"]["phases"] == "variable":   # pooled phases start at default
            self._em(basis, weights, tg, state)
        cost = float(torque.solve_weights(basis, weights, tg).sum())
        m, ok = self._metrics(basis, weights, tg, state, figures=True)
        self.log_model(basis, weights, state["step"])
        state["model"] = model_state(basis, weights)
        state["history"]["pool"] = {"M": basis.M, "merged": merged, "torque_cost": cost,
                                    "success": ok}
        state["reduce_base"] = {"rmse": m["rmse"], "tip": m["tip"], "ok": ok}
        self.status("pool", M=basis.M, cost=cost, ok=sum(ok))
        self._advance(state, "reduce")
        state["order"] = None
        self.save(state)

    def _stage_reduce(self, state, tg):
        """Backward elimination. With model.fields = 0 a field goes only if no motion gets
        worse (:func:`no_worse`); with model.fields = M the smallest-share fields go
        until M remain."""
        fixed = self.cfg["model"]["fields"]
        basis, weights = model_from_state(state["model"])
        if state.get("order") is None:
            shares = search.field_shares(basis, weights, tg)
            state["order"] = [int(i) for i in torch.argsort(shares)]
            state["ids"] = list(range(basis.M))
        k = state["cursor"]
        if basis.M <= max(fixed, 1) or k >= len(state["order"]):
            return self._advance(state, "path")
        victim = state["order"][k]
        state["cursor"] = k + 1
        pos = state["ids"].index(victim)
        keep = [i for i in range(basis.M) if i != pos]
        nb, nw = search.keep_fields(basis, weights, keep)
        self._em(nb, nw, tg, state)
        if fixed:
            accept = True
        else:
            m, ok = self._metrics(nb, nw, tg, state)
            accept = no_worse(state["reduce_base"], m, ok)
        if accept:
            state["model"] = model_state(nb, nw)
            state["ids"] = [state["ids"][i] for i in keep]
            if not fixed:
                state["reduce_base"] = {"rmse": m["rmse"], "tip": m["tip"], "ok": ok}
        self.status("reduce", M=len(state["ids"]), removed=float(accept))
        state["history"].setdefault("reduce", []).append(
            {"field": victim, "removed": bool(accept), "M_after": len(state["ids"])})
        self.save(state)

    def _stage_path(self, state, tg):
        p = self.cfg["solver"]["path"]
        basis, weights = model_from_state(state["model"])
        if state["cursor"] == 0:
            m, ok = self._metrics(basis, weights, tg, state)
            state["path_needed"] = not all(ok)
            state["path_lr"] = p["lr"]
            state["path_opt"] = None
            state["path_best"] = None
        if not state["path_needed"] or state["cursor"] >= p["steps"]:
            return self._advance(state, "done")
        try:
            res = path_fit.path_step(self.body, basis, weights, tg, lr=state["path_lr"],
                                     best=state["path_best"], optimizer_state=state["path_opt"],
                                     velocity_weight=p["velocity_weight"], adjoint=p["adjoint"],
                                     phases=self.cfg["model"]["phases"] == "variable",
                                     **self._sim_kw())
        except RuntimeError as err:          # the simulation fails at the starting point
            state["history"]["path"] = str(err)
            self.status("path", failed=1.0)
            return self._advance(state, "done")
        state["path_lr"], state["path_best"], state["path_opt"] = res["lr"], res["best"], res["optimizer"]
        state["model"] = model_state(basis, weights)
        state["step"] += 1
        self.scalar("path/loss", res["loss"], state["step"])
        self.status("path", loss=res["loss"], lr=res["lr"])
        state["cursor"] += 1
        self.save(state)

    def _stage_slsqp(self, state, tg):
        gen = self._gen(state)
        M, n = self.cfg["model"]["fields"], tg.q.shape[-1]
        flat = tg.q[tg.mask]
        eta = flat[torch.randint(len(flat), (M,), generator=gen)]
        basis = FieldBasis(eta, torch.eye(n, dtype=torch.float64).expand(M, n, n).clone(), kind="diag")
        z = torch.zeros(tg.N, M, dtype=torch.float64)
        weights = MotionWeights(z, z, tg.duration, names=tg.names)
        torque.solve_weights(basis, weights, tg)

        def cb(nit, cost):
            state["step"] += 1
            self.scalar("torque/cost_total", cost, state["step"])
            self.status("slsqp", iteration=nit, cost=cost)
        res = slsqp.fit_slsqp(basis, weights, tg, max_iter=self.cfg["solver"]["slsqp"]["max_iter"],
                              callback=cb)
        state["model"] = model_state(res["basis"], res["weights"])
        state["history"]["slsqp"] = {k: res[k] for k in ("initial_cost", "cost", "nit", "nfev",
                                                          "message", "wall_time")}
        state["rng"] = gen.get_state()
        self._advance(state, "done")
        self.save(state)

    # ---- artefacts
    def finish(self, state, tg) -> dict:
        basis, weights = model_from_state(state["model"])
        if state.get("path_best") is not None:
            basis.load_state_dict(state["path_best"]["basis"])
            weights.load_state_dict(state["path_best"]["weights"])
        m, ok = self._metrics(basis, weights, tg, state, figures=True)
        rate = torch.tensor([1.0 / float(tg.t[j, 1] - tg.t[j, 0]) for j in range(tg.N)],
                            dtype=torch.float64)
        lb = basis_io.LearnedBasis(self.body, basis, weights, tg.q0, tg.qd0, rate)
        basis_io.save(lb, self.out / "basis.json")
        metrics = summarize(m, ok, tg, basis.M, state.get("elapsed", 0.0) + time.time() - self._t0)
        for name, eps in zip(tg.names, self.resolution):
            metrics["motions"][name]["torque_resolution"] = eps
        metrics["history"] = state["history"]
        (self.out / "metrics.json").write_text(json.dumps(metrics, indent=1))
        config_mod.dump(self.cfg, self.out / "config.yaml")
        if self.writer:
            hp = {"seed": self.cfg["seed"], "stiffness": self.cfg["model"]["stiffness"],
                  "phases": self.cfg["model"]["phases"], "data": str(self.cfg["data"])}
            self.writer.add_hparams(hp, {"hparam/M": basis.M,
                                         "hparam/rmse": metrics["overall"]["rmse"],
                                         "hparam/tip": metrics["overall"]["tip"],
                                         "hparam/success": float(all(ok))})
        write_figures(self.body, tg, m, self.out)
        if state["stage"] != "done" or not self.ckpt_path.exists():
            state["stage"] = "done"
        torch.save(state, self.ckpt_path)
        return metrics


def no_worse(base: dict, m: dict, ok: list) -> bool:
    """Whether a smaller basis keeps every motion as good as ``base`` ({"rmse", "tip",
    "ok"}, per motion): a motion reproduced stays reproduced; one not reproduced has
    joint RMSE and tip error no larger than before."""
    return all(now if was else (r <= r0 and p <= p0)
               for was, now, r, r0, p, p0 in zip(base["ok"], ok, m["rmse"], base["rmse"],
                                                 m["tip"], base["tip"]))


def summarize(m: dict, ok: list, tg: Targets, M: int, wall: float) -> dict:
    """metrics.json: per motion and overall joint RMSE, max tip error, torque error."""
    per = {name: {"rmse": m["rmse"][j], "tip": m["tip"][j], "torque_rel_rms": m["torque"][j],
                  "success": ok[j]} for j, name in enumerate(tg.names)}
    counts = tg.mask.sum(-1).double()
    overall_rmse = float(((torch.tensor(m["rmse"], dtype=torch.float64) ** 2 * counts).sum()
                          / counts.sum()).sqrt())
    return {"motions": per,
            "overall": {"rmse": overall_rmse, "tip": max(m["tip"]),
                        "torque_rel_rms": max(m["torque"]), "success": all(ok),
                        "M": M, "wall_time_s": wall}}


def write_figures(body, tg: Targets, m: dict, out: Path) -> None:
    from . import plots
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    for j, name in enumerate(tg.names):
        k = int(tg.mask[j].sum())
        plots.save(plots.motion_sheet(body, tg.t[j, :k], {"target": tg.q[j, :k],
                                                          "simulated": m["q_sim"][j, :k]},
                                      title=f"{name}: rmse {m['rmse'][j]:.4f} rad, "
                                            f"tip {100 * m['tip'][j]:.2f} cm"),
                   fig_dir / f"{name}.png")


def run(cfg: dict, restart: bool = False, stop_after: int | None = None,
        progress: bool | None = None) -> dict:
    """Train with a resolved config (see :mod:`tflearn.config`); returns metrics.json's dict."""
    return Run(cfg, stop_after=stop_after, progress=progress).execute(restart=restart)
