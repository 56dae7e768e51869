"""The thesis' chapter 4 experiments, each run end to end from ``configs/experiments/NAME.yaml``.

    tflearn experiment NAME [--quick] [--jobs N] [key=value ...]  → OUT/results.json, OUT/figures/
    tflearn report                                                  → docs/results.md + its figures

Experiments (``EXPERIMENTS``):

* ``basin`` (§4.1) — each gesture alone; its generating parameters θ (η, scalar k, a, b)
  each multiplied by an independent factor 1 + (r − 1)u, u ~ U[0, 1] (a seed fixes the
  u's; zeros stay zero, as in the thesis), handed as the initial guess to
  ``slsqp`` (the thesis' method, :func:`tflearn.fit.slsqp.fit_slsqp`), ``local`` (EM,
  then path matching when EM's fit is near but not reproduced) and ``pipeline`` (the
  full :mod:`tflearn.train` search, which ignores the guess — one run per seed stands
  for every r).
* ``shared`` (§4.2) — come-here, tuck and backwards reach together with four fields; the
  same three methods from the four generating fields noised, the pipeline with M = 4.
* ``keyframes`` (§4.3) — three-keyframe eased spline animations resembling each gesture
  and a straight-line reach of the hand (:mod:`tflearn.keyframes`), learned together
  by the pipeline; M is found.
* ``filtering`` (§4.5.4) — crude motions (a straight-line reach, a two-keyframe move)
  played through a basis learned on the gestures: only their weights are fitted
  (:func:`tflearn.evaluate.synthesize`), and the simulation adds the fields' curvature.

Success everywhere means the simulated path has joint RMSE ≤ ``success.rmse`` and hand
tip error ≤ ``success.tip``. Costs (experiment 5) are the methods' wall times and
numbers of simulations (:data:`tflearn.simulate.calls`), as ratios to SLSQP measured in
the same run. Cases are cached in OUT/cases/, so an interrupted experiment resumes.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import torch

from . import config as config_mod
from . import gestures as gestures_mod
from . import simulate as sim_mod
from .body import Body, arm
from .fields import FieldBasis, MotionWeights
from .fit import path as path_fit
from .fit import torque
from .fit.slsqp import fit_slsqp
from .fit.targets import Targets, prepare
from .motion import save as save_motion

F64 = torch.float64
EXPERIMENTS = ("basin", "shared", "keyframes", "filtering")
METHODS = ("slsqp", "local", "pipeline")

#: Thesis chapter 4 outcomes: for each gesture, the largest r recovered and the first r
#: that failed (§4.1, figures 4-1 to 4-5); §4.2's four-field runs (figures 4-6 to 4-8).
THESIS = {
    "basin": {"come_here": (2.6, 3.0), "stiff_elbow_lift": (1.4, 1.8), "tuck": (3.8, 4.2),
              "planar_line": (2.2, 2.6), "backwards_reach": (2.2, 2.6)},
    "shared": "Four fields for come-here, tuck and backwards reach from noised parameters: "
              "the tuck recovered at r = 2.2 but failed by r = 2.6-3.0 (less robust than "
              "alone), the backwards reach recovered up to r = 3.0 (more robust than alone); "
              "no run from no initial guess.",
    "keyframes": "A three-keyframe spline resembling the come-here, matched with the four-field "
                 "basis of §4.2: 'catastrophic results' (figure 4-9). No motion not made by "
                 "torque fields was reproduced.",
    "filtering": "Proposed as future work (§4.5.4), not tried.",
}

_TRAIN = config_mod.merge(config_mod.DEFAULTS, {"log": {"tensorboard": False, "progress": False}})
_SCHEMA = {
    "experiment": "basin",
    "out": "runs/experiments/basin",
    "gestures": list(gestures_mod.GESTURES),   # the gestures of basin / shared / keyframes
    "r": [1.2, 1.4, 1.8, 2.2, 2.6, 3.0, 4.2, 6.0, 8.0, 10.0],
    "seeds": 20,
    "seed0": 0,
    "methods": list(METHODS),
    "straight_reach": True,            # keyframes: add the straight-line reach of the hand
    "jobs": 1,
    "slsqp": {"max_iter": 200, "ftol": 1e-12},
    # EM steps; path matching only where EM's relative torque cost is ≤ path_gate
    "local": {"em_steps": 300, "em_tol": 1e-10, "path_steps": 15, "path_lr": 0.01,
              "path_gate": 1e-3},
    "simulation": {"method": "dopri5", "rtol": 1e-6, "atol": 1e-8, "budget": 15000},
    "success": {"rmse": 0.03, "tip": 0.02},
    "train": _TRAIN,                   # the pipeline's training config (tflearn.config keys)
}
DEFAULTS = _SCHEMA


def load_config(path, quick: bool = False, overrides=()) -> dict:
    """An experiment config: :data:`DEFAULTS` ← the file ← its ``quick:`` section (with
    ``quick``) ← dotted ``key=value`` overrides. Unknown keys and bad values raise
    :class:`~tflearn.config.ConfigError` naming the file and the key."""
    doc = config_mod.read(path)
    quick_doc = doc.pop("quick", None) or {}
    try:
        config_mod.check(doc, DEFAULTS)
        config_mod.check(quick_doc, DEFAULTS, "quick.")
        cfg = config_mod.merge(DEFAULTS, doc)
        if quick:
            cfg = config_mod.merge(cfg, quick_doc)
        if overrides:
            cfg = config_mod.load(None, overrides, defaults=cfg)
        if cfg["experiment"] not in EXPERIMENTS:
            raise config_mod.ConfigError(f"experiment must be one of {EXPERIMENTS}, "
                                         f"got {cfg['experiment']!r}")
        unknown = [g for g in cfg["gestures"] if g not in gestures_mod.GESTURES]
        if unknown:
            raise config_mod.ConfigError(f"unknown gestures {unknown} (known: {list(gestures_mod.GESTURES)})")
        bad = [m for m in cfg["methods"] if m not in METHODS]
        if bad:
            raise config_mod.ConfigError(f"unknown methods {bad} (known: {list(METHODS)})")
    except config_mod.ConfigError as err:
        raise config_mod.ConfigError(f"{path}: {err}") from None
    cfg["quick"] = quick
    return cfg


# ------------------------------------------------------------ initial guesses (thesis §4.1)

def generating(gestures: list) -> dict:
    """The generating parameters of a group of gestures sharing one basis:
    {"eta": M×n, "k": M, "a": N×M, "b": N×M} (:func:`tflearn.gestures.library_model`)."""
    basis, weights, _ = gestures_mod.library_model(gestures)
    with torch.no_grad():
        return {"eta": basis.eta.clone(), "k": basis.K()[:, 0, 0].clone(),
                "a": weights.a.clone(), "b": weights.b.clone()}


def noise_draws(true: dict, seed: int, salt: int) -> dict:
    """u ~ U[0, 1] for every entry of θ, from a generator seeded by (seed, salt)."""
    gen = torch.Generator().manual_seed(1_000_003 * seed + 7919 * salt + 17)
    return {key: torch.rand(true[key].shape, generator=gen, dtype=F64) for key in ("eta", "k", "a", "b")}


def noised(true: dict, u: dict, r: float) -> dict:
    """θ · (1 + (r − 1) u): each parameter times a factor in [1, r] (zeros stay zero)."""
    return {key: true[key] * (1 + (r - 1) * u[key]) for key in true}


def build(guess: dict, tg: Targets, kind: str = "diag"):
    """A fresh (FieldBasis, MotionWeights) holding a guess, K = k·I."""
    n = guess["eta"].shape[-1]
    K = guess["k"][:, None, None] * torch.eye(n, dtype=F64)
    basis = FieldBasis(guess["eta"].clone(), K, kind=kind)
    return basis, MotionWeights(guess["a"].clone(), guess["b"].clone(), tg.duration, names=tg.names)


# ------------------------------------------------------------------- reproduction check

def check(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets, cfg: dict) -> dict:
    """Simulate every motion of ``tg``: {"rmse", "tip", "success" (lists, N), "q_sim"}.
    A simulation that fails or needs more than ``simulation.budget`` right-hand-side
    evaluations counts as not reproduced (:func:`tflearn.fit.path.metrics`)."""
    s = cfg["simulation"]
    m = path_fit.metrics(body, basis, weights, tg, method=s["method"], rtol=s["rtol"],
                         atol=s["atol"], max_evals=s["budget"])
    m["success"] = path_fit.succeeded(m, cfg["success"]["rmse"], cfg["success"]["tip"])
    return m


def _params(basis: FieldBasis, weights: MotionWeights) -> dict:
    with torch.no_grad():
        return {"eta": basis.eta.tolist(), "K": basis.K().tolist(), "a": weights.a.tolist(),
                "b": weights.b.tolist()}


def _model(params: dict, tg: Targets):
    basis = FieldBasis(torch.tensor(params["eta"], dtype=F64), torch.tensor(params["K"], dtype=F64),
                       kind="full")
    a, b = torch.tensor(params["a"], dtype=F64), torch.tensor(params["b"], dtype=F64)
    return basis, MotionWeights(a, b, tg.duration, names=tg.names)


# --------------------------------------------------------------------------- the methods

def fit_slsqp_case(body, guess: dict, tg: Targets, cfg: dict) -> dict:
    """The thesis' method from a guess: SLSQP on the torque cost, then one simulation."""
    basis, weights = build(guess, tg)
    history = []
    res = fit_slsqp(basis, weights, tg, max_iter=cfg["slsqp"]["max_iter"],
                    ftol=cfg["slsqp"]["ftol"], callback=lambda it, c: history.append(c))
    return {"basis": res["basis"], "weights": res["weights"], "cost": res["cost"],
            "wall": res["wall_time"], "evals": res["nfev"], "sims": 0,
            "history": [res["initial_cost"]] + history}


def fit_local_case(body, guess: dict, tg: Targets, cfg: dict) -> dict:
    """tflearn's local solver from a guess: EM (exact NNLS weights + Levenberg–Marquardt
    on the fields), first with the weights the guess leaves at zero held there, then
    with all weights free; if its fit is near (relative torque cost ≤ ``local.path_gate``)
    but not reproduced, path matching of fields and weights through ``odeint``. The
    returned "check" is the simulation that found the fit reproduced (None if it was not
    simulated or was changed since), so that it is not simulated twice.

    The first phase keeps EM local: unrestricted, its first NNLS solve may switch on a
    profile the guess has off (e.g. a large pulse on a step-only gesture) and descend
    into that profile's basin, a local minimum that the guess was not near."""
    c, s = cfg["local"], cfg["simulation"]
    basis, weights = build(guess, tg)
    calls0, t0 = sim_mod.calls, time.perf_counter()
    support = torch.cat([guess["a"] != 0, guess["b"] != 0], dim=-1)
    history = torque.em(basis, weights, tg, steps=c["em_steps"], tol=c["em_tol"], support=support)
    history += torque.em(basis, weights, tg, steps=c["em_steps"], tol=c["em_tol"])[1:]
    cost = history[-1]
    m = check(body, basis, weights, tg, cfg) if c["path_steps"] and cost <= c["path_gate"] else None
    if m is not None and not all(m["success"]):
        try:
            path_fit.path_match(body, basis, weights, tg, steps=c["path_steps"], lr=c["path_lr"],
                                method=s["method"], rtol=s["rtol"], atol=s["atol"])
        except RuntimeError:                         # the simulation fails at the start
            pass
        with torch.no_grad():
            cost = float(torque.torque_cost(basis, weights, tg).sum())
        m = None
    return {"basis": basis, "weights": weights, "cost": cost, "wall": time.perf_counter() - t0,
            "evals": len(history), "sims": sim_mod.calls - calls0, "history": history, "check": m}


def fit_pipeline_case(body, motions: list, cfg: dict, out: Path, seed: int) -> dict:
    """tflearn's full search (:mod:`tflearn.train`, no initial guess) on ``motions``."""
    from . import train
    from .io import basis as basis_io
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for m in motions:
        save_motion(m, out / f"{m.name}.npz")
        files.append(str(out / f"{m.name}.npz"))
    tcfg = config_mod.merge(cfg["train"], {"data": files, "out": str(out / "run"), "seed": seed,
                                           "success": cfg["success"]})
    calls0 = sim_mod.calls
    metrics = train.run(tcfg, progress=False)
    wall, sims = metrics["overall"]["wall_time_s"], sim_mod.calls - calls0   # wall: over resumes
    lb = basis_io.load(out / "run" / "basis.json")
    return {"basis": lb.basis, "weights": lb.weights, "metrics": metrics, "wall": wall,
            "sims": sims, "M": metrics["overall"]["M"]}


# --------------------------------------------------------------------------- case runner

_STATE: dict = {}


def _row(method: str, group: str, r, seed: int, fit: dict, m: dict, names: list) -> dict:
    row = {"group": group, "method": method, "r": r, "seed": seed, "motions": names,
           "success": m["success"], "rmse": m["rmse"], "tip": m["tip"],
           "wall": fit["wall"], "sims": fit["sims"]}
    for key in ("cost", "evals", "history", "M"):
        if key in fit:
            row[key] = fit[key]
    if "basis" in fit:
        row["params"] = _params(fit["basis"], fit["weights"])
    if "error" in m:
        row["error"] = m["error"]
    return row


def run_case(case: tuple) -> list:
    """One unit of work: ("noised", group, r, seed) runs every guess-based method from the
    same guess; ("pipeline", group, None, seed) runs the full search once."""
    torch.set_num_threads(1)
    kind, group, r, seed = case
    cfg, body = _STATE["cfg"], _STATE["body"]
    names, motions, tg, true, salt = _STATE["groups"][group]
    if kind == "pipeline":
        fit = fit_pipeline_case(body, motions, cfg, Path(cfg["out"]) / "pipeline" / f"{group}-s{seed}", seed)
        per = fit["metrics"]["motions"]
        m = {"success": [per[n]["success"] for n in names], "rmse": [per[n]["rmse"] for n in names],
             "tip": [per[n]["tip"] for n in names]}
        fit.pop("basis")
        return [_row("pipeline", group, None, seed, fit, m, names)]
    guess = noised(true, noise_draws(true, seed, salt), r)
    rows = []
    for method in (x for x in cfg["methods"] if x != "pipeline"):
        fit = (fit_slsqp_case if method == "slsqp" else fit_local_case)(body, guess, tg, cfg)
        m = fit.pop("check", None)
        if m is None:
            m = check(body, fit["basis"], fit["weights"], tg, cfg)
        if cfg["experiment"] != "shared":
            fit.pop("history")
        rows.append(_row(method, group, r, seed, fit, m, names))
    return rows


def _case_file(cfg: dict, case: tuple) -> Path:
    kind, group, r, seed = case
    tag = f"{kind}-{group}-s{seed}" + ("" if r is None else f"-r{r:g}")
    return Path(cfg["out"]) / "cases" / f"{tag}.json"


def run_cases(cfg: dict, cases: list) -> list:
    """All cases (cached in OUT/cases/: a re-run skips the ones done), ``jobs`` at a time."""
    from tqdm import tqdm
    todo = [c for c in cases if not _case_file(cfg, c).exists()]
    bar = tqdm(total=len(cases), initial=len(cases) - len(todo), desc=cfg["experiment"],
               disable=None)

    def store(case, rows):
        path = _case_file(cfg, case)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(rows))
        bar.update()
        bar.set_postfix_str(f"{case[1]} r={case[2]} seed={case[3]}: " + ", ".join(
            f"{x['method']} {sum(x['success'])}/{len(x['success'])}" for x in rows))
    if cfg["jobs"] > 1 and len(todo) > 1:
        import multiprocessing as mp
        with mp.get_context("fork").Pool(cfg["jobs"]) as pool:
            for case, rows in zip(todo, pool.imap(run_case, todo)):
                store(case, rows)
    else:
        for case in todo:
            store(case, run_case(case))
    bar.close()
    return [row for c in cases for row in json.loads(_case_file(cfg, c).read_text())]


# ------------------------------------------------------------------------ the experiments

def _setup(cfg: dict, groups: dict) -> None:
    """Generate the gestures of every group and prepare their targets."""
    body = arm()
    names = sorted({g for gs in groups.values() for g in gs}, key=list(gestures_mod.GESTURES).index)
    motions = {m.name: m for m, _ in gestures_mod.generate(
        body, gestures=[gestures_mod.GESTURES[n] for n in names])}
    state = {}
    for group, gs in groups.items():
        ms = [motions[g] for g in gs]
        salt = list(gestures_mod.GESTURES).index(gs[0]) if len(gs) == 1 else \
            1000 + sum(list(gestures_mod.GESTURES).index(g) for g in gs)
        state[group] = (list(gs), ms, prepare(body, ms),
                        generating([gestures_mod.GESTURES[g] for g in gs]), salt)
    _STATE.update(cfg=cfg, body=body, groups=state)


def _noise_cases(cfg: dict, groups: dict) -> list:
    seeds = range(cfg["seed0"], cfg["seed0"] + cfg["seeds"])
    cases = []
    for group in groups:
        if "pipeline" in cfg["methods"]:
            cases += [("pipeline", group, None, s) for s in seeds]
        if set(cfg["methods"]) - {"pipeline"}:
            cases += [("noised", group, r, s) for r in cfg["r"] for s in seeds]
    return cases


def success_rates(rows: list, cfg: dict) -> dict:
    """{group: {method: {"r": [...], "rate": [...] (all motions of the case reproduced),
    "per_motion": {name: [...]}}}}; the pipeline's runs (independent of r) count at every r."""
    out = {}
    for group in dict.fromkeys(x["group"] for x in rows):
        out[group] = {}
        for method in cfg["methods"]:
            sel = [x for x in rows if x["group"] == group and x["method"] == method]
            if not sel:
                continue
            rates, per = [], {n: [] for n in sel[0]["motions"]}
            for r in cfg["r"]:
                at = [x for x in sel if x["r"] is None or x["r"] == r]
                rates.append(sum(all(x["success"]) for x in at) / len(at))
                for k, n in enumerate(sel[0]["motions"]):
                    per[n].append(sum(x["success"][k] for x in at) / len(at))
            out[group][method] = {"r": list(cfg["r"]), "rate": rates, "per_motion": per,
                                  "cases": len([x for x in sel if x["r"] in (None, cfg["r"][0])])}
    return out


def r90(r: list, rate: list) -> float:
    """The largest r of the sweep up to which (every r ≤ it) the success rate is ≥ 90%
    (0 if the first r already fails)."""
    best = 0.0
    for x, p in zip(r, rate):
        if p < 0.9:
            break
        best = x
    return best


def costs(rows: list) -> dict:
    """Experiment 5: per method, total wall time and simulations, and their ratios to SLSQP."""
    out = {}
    for method in dict.fromkeys(x["method"] for x in rows):
        sel = [x for x in rows if x["method"] == method]
        wall = sum(x["wall"] for x in sel)
        out[method] = {"runs": len(sel), "wall_s": wall, "wall_per_run_s": wall / len(sel),
                       "sims": sum(x["sims"] for x in sel)}
    ref = out.get("slsqp")
    for v in out.values():
        v["wall_ratio"] = v["wall_s"] / ref["wall_s"] if ref and ref["wall_s"] else None
        v["run_ratio"] = v["wall_per_run_s"] / ref["wall_per_run_s"] if ref and ref["wall_s"] else None
        v["sims_per_run"] = v["sims"] / v["runs"]
    return out


def _noise_experiment(cfg: dict, groups: dict) -> dict:
    """Every method from noised guesses, for each group of gestures sharing a basis."""
    _setup(cfg, groups)
    rows = run_cases(cfg, _noise_cases(cfg, groups))
    rates = success_rates(rows, cfg)
    summary = {"rates": rates, "costs": costs(rows), "r90": {
        g: {m: r90(v["r"], v["rate"]) for m, v in ms.items()} for g, ms in rates.items()}}
    return {"rows": rows, "summary": summary}


def basin(cfg: dict) -> dict:
    """Experiment 1 (§4.1): success rate against r, per gesture alone and method."""
    return _noise_experiment(cfg, {g: [g] for g in cfg["gestures"]})


def shared(cfg: dict) -> dict:
    """Experiment 2 (§4.2): several gestures, one basis of their generating fields."""
    return _noise_experiment(cfg, {"+".join(cfg["gestures"]): cfg["gestures"]})


def _gesture_motions(body: Body, names: list) -> dict:
    gs = [gestures_mod.GESTURES[n] for n in names]
    return {m.name: m for m, _ in gestures_mod.generate(body, gestures=gs)}


def keyframe_motions(body: Body, names: list, reach: bool = True) -> list:
    """§4.3's motions: for each gesture a three-keyframe eased spline through its postures
    at the start, the middle and the end, and (with ``reach``) a straight-line reach of
    the hand from rest to where the planar line ends."""
    from . import dynamics
    from .keyframes import keyframe_motion, straight_reach
    source = _gesture_motions(body, list(dict.fromkeys(names + ["planar_line"])))
    out = []
    for n in names:
        m = source[n]
        T = len(m.t)
        out.append(keyframe_motion(f"{n}_keys", body, m.q[[0, T // 2, T - 1]],
                                   [0.0, float(m.t[T // 2]), float(m.t[-1])]))
    if reach:
        end = dynamics.tip_position(body, source["planar_line"].q[-1])
        out.append(straight_reach("straight_reach", body, torch.zeros(body.nv, dtype=F64), end, 3.0))
    return out


def keyframes(cfg: dict) -> dict:
    """Experiment 3 (§4.3): motions not made by torque fields, each learned by the
    pipeline (its own basis, M found); the thesis' method (SLSQP from the four generating
    fields of §4.2, weights from NNLS, all motions together) as the baseline."""
    body = arm()
    motions = keyframe_motions(body, cfg["gestures"], cfg["straight_reach"])
    names = [m.name for m in motions]
    tg = prepare(body, motions)
    rows = []
    if "slsqp" in cfg["methods"]:
        guess = generating([gestures_mod.GESTURES[g] for g in ("come_here", "tuck", "backwards_reach")])
        basis, weights = build({**guess, "a": torch.zeros(tg.N, 4, dtype=F64),
                                "b": torch.zeros(tg.N, 4, dtype=F64)}, tg)
        torque.solve_weights(basis, weights, tg)
        with torch.no_grad():
            start = {"eta": basis.eta.clone(), "k": guess["k"], "a": weights.a.clone(), "b": weights.b.clone()}
        fit = fit_slsqp_case(body, start, tg, cfg)
        fit.pop("history")
        rows.append(_row("slsqp", "keyframes", None, cfg["seed0"], fit,
                         check(body, fit["basis"], fit["weights"], tg, cfg), names))
    if "pipeline" in cfg["methods"]:
        for motion in motions:                         # each motion its own basis, M found
            fit = fit_pipeline_case(body, [motion], cfg, Path(cfg["out"]) / "pipeline" / motion.name,
                                    cfg["seed0"])
            per = fit["metrics"]["motions"][motion.name]
            m = {"success": [per["success"]], "rmse": [per["rmse"]], "tip": [per["tip"]]}
            rows.append(_row("pipeline", motion.name, None, cfg["seed0"], fit, m, [motion.name]))
    return {"rows": rows, "summary": {"costs": costs(rows)}}


def straightness(body: Body, q) -> float:
    """Largest distance of the hand path from its chord, relative to the chord's length."""
    from . import dynamics
    p = dynamics.tip_position(body, torch.as_tensor(q, dtype=F64))
    chord = p[-1] - p[0]
    u = chord / chord.norm()
    d = p - p[0]
    off = d - (d @ u)[:, None] * u
    return float(off.norm(dim=-1).max() / chord.norm())


def crude_motions(body: Body) -> list:
    """§4.5.4's crude inputs: a straight-line hand reach from rest to straight ahead (where
    the stiff-elbow lift ends) and a two-keyframe move from rest to the tuck's end posture."""
    from . import dynamics
    from .keyframes import keyframe_motion, straight_reach
    src = _gesture_motions(body, ["stiff_elbow_lift", "tuck"])
    zero = torch.zeros(body.nv, dtype=F64)
    reach = straight_reach("straight_reach", body, zero,
                           dynamics.tip_position(body, src["stiff_elbow_lift"].q[-1]), 3.0)
    move = keyframe_motion("two_key_move", body, torch.stack([zero, src["tuck"].q[-1]]), [0.0, 3.0])
    return [reach, move]


def filtering(cfg: dict) -> dict:
    """Experiment 4 (§4.5.4): crude motions through a basis learned on the gestures."""
    from .evaluate import synthesize
    from .io import basis as basis_io
    body = arm()
    learned = fit_pipeline_case(body, list(_gesture_motions(body, cfg["gestures"]).values()), cfg,
                                Path(cfg["out"]) / "pipeline" / f"s{cfg['seed0']}", cfg["seed0"])
    lb = basis_io.load(Path(cfg["out"]) / "pipeline" / f"s{cfg['seed0']}" / "run" / "basis.json")
    motions = crude_motions(body)
    tg = prepare(body, motions)
    c, s = cfg["local"], cfg["simulation"]
    calls0, t0 = sim_mod.calls, time.perf_counter()
    weights = synthesize(lb, tg, c["path_steps"], c["path_lr"], method=s["method"],
                         rtol=s["rtol"], atol=s["atol"])
    fit = {"basis": lb.basis, "weights": weights, "wall": time.perf_counter() - t0,
           "sims": sim_mod.calls - calls0}
    m = check(body, lb.basis, weights, tg, cfg)
    row = _row("filter", "crude", None, cfg["seed0"], fit, m, tg.names)
    row["straightness_in"] = [straightness(body, x.q) for x in motions]
    row["straightness_out"] = [straightness(body, m["q_sim"][j, :len(x.t)]) for j, x in enumerate(motions)]
    basis_row = {"group": "gestures", "method": "pipeline", "r": None, "seed": cfg["seed0"],
                 "motions": list(learned["metrics"]["motions"]),
                 "success": [v["success"] for v in learned["metrics"]["motions"].values()],
                 "rmse": [v["rmse"] for v in learned["metrics"]["motions"].values()],
                 "tip": [v["tip"] for v in learned["metrics"]["motions"].values()],
                 "wall": learned["wall"], "sims": learned["sims"], "M": learned["M"]}
    return {"rows": [basis_row, row], "summary": {"costs": costs([basis_row, row])}}


# ------------------------------------------------------------------------------ figures

def _resimulate(body, params, tg, cfg):
    basis, weights = _model(params, tg)
    return check(body, basis, weights, tg, cfg)["q_sim"]


def _pipeline_q(body, cfg, run_dir: Path, tg: Targets):
    """The simulated paths of a pipeline run's basis on ``tg`` (its own motions)."""
    from .evaluate import weights_for
    from .io import basis as basis_io
    lb = basis_io.load(run_dir / "basis.json")
    return check(body, lb.basis, weights_for(lb, tg), tg, cfg)["q_sim"], lb


def _sheets(body, tg: Targets, sims: dict, fig_dir: Path) -> list:
    """Per motion, target vs each simulated path of ``sims`` (label → N×T×n): a sheet of
    joint trajectories and 3-D hand paths, and a stick-figure strip."""
    from . import plots
    paths = []
    for j, name in enumerate(tg.names):
        k = int(tg.mask[j].sum())
        p = {"target": tg.q[j, :k]}
        p.update({label: q[j, :k] for label, q in sims.items() if q is not None})
        title = f"{name}: " + ", ".join(p)
        path, strip = fig_dir / f"{name}.png", fig_dir / f"{name}_strip.png"
        plots.save(plots.motion_sheet(body, tg.t[j, :k], p, title=title), path)
        plots.save(plots.stick_strip(body, p, title=title), strip)
        paths += [path, strip]
    return paths


def _animations(run_dir: Path, names: list, fig_dir: Path) -> list:
    """A GIF per motion of a pipeline run: target and reproduced arm (:mod:`tflearn.render`)."""
    from .render import render
    return [render(run_dir, name, out=fig_dir / f"{name}.gif", fps=10, tensorboard=False,
                   log=lambda line: None) for name in names]


def success_figure(rates: dict, thesis: dict | None, per_motion: bool = False):
    """Success rate against r: one panel per group (or per motion), a line per method;
    the thesis' largest recovered r (green) and first failed r (red) dashed."""
    from . import plots  # noqa: F401  (selects the Agg backend)
    import matplotlib.pyplot as plt
    panels = []
    for group, ms in rates.items():
        if per_motion:
            first = next(iter(ms.values()))
            panels += [(name, {m: (v["r"], v["per_motion"][name]) for m, v in ms.items()})
                       for name in first["per_motion"]]
        else:
            panels.append((group, {m: (v["r"], v["rate"]) for m, v in ms.items()}))
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.2), squeeze=False)
    for ax, (name, lines) in zip(axes[0], panels):
        for method, (r, rate) in lines.items():
            ax.plot(r, [100 * x for x in rate], "o-", ms=3, label=method)
        if thesis and name in thesis:
            ok, fail = thesis[name]
            ax.axvline(ok, color="g", ls="--", lw=0.8, label="thesis: recovered")
            ax.axvline(fail, color="r", ls="--", lw=0.8, label="thesis: failed")
        ax.set_xscale("log")
        ax.set_xticks([1.2, 1.5, 2, 3, 5, 10], ["1.2", "1.5", "2", "3", "5", "10"])
        ax.minorticks_off()
        ax.set_xlabel("r")
        ax.set_title(name, fontsize=9)
        ax.set_ylim(-5, 105)
    axes[0, 0].set_ylabel("reproduced (%)")
    axes[0, 0].legend(fontsize=6)
    fig.tight_layout()
    return fig


def figures(cfg: dict, result: dict) -> list:
    """The experiment's PNGs in OUT/figures (returned as paths)."""
    from . import plots
    fig_dir = Path(cfg["out"]) / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    body, rows, exp = arm(), result["rows"], cfg["experiment"]
    out = []
    if exp in ("basin", "shared"):
        rates = result["summary"]["rates"]
        path = fig_dir / "success_vs_r.png"
        plots.save(success_figure(rates, THESIS["basin"] if exp == "basin" else None,
                                  per_motion=exp == "shared"), path)
        out.append(path)
        for group in rates:
            tg = _STATE["groups"][group][2]
            limit = THESIS["basin"].get(group, (2.2, 2.6))[1]
            r_show = min((r for r in cfg["r"] if r >= limit), default=cfg["r"][-1])
            sims = {}
            for method in ("slsqp", "local"):
                row = next((x for x in rows if x["group"] == group and x["method"] == method
                            and x["r"] == r_show and x["seed"] == cfg["seed0"]), None)
                if row:
                    sims[f"{method} r={r_show:g}"] = _resimulate(body, row["params"], tg, cfg)
            run_dir = Path(cfg["out"]) / "pipeline" / f"{group}-s{cfg['seed0']}" / "run"
            if (run_dir / "basis.json").exists():
                sims["pipeline"], lb = _pipeline_q(body, cfg, run_dir, tg)
                out += _animations(run_dir, tg.names, fig_dir)
                if exp == "shared":
                    path = fig_dir / "weights.png"
                    plots.save(plots.weights_bars(lb.names, lb.weights.a.detach(), lb.weights.b.detach(),
                                                  title="pipeline (M = 4): weights per motion"), path)
                    out.append(path)
            out += _sheets(body, tg, sims, fig_dir)
        if exp == "shared":
            curves = {f"{x['method']} r={x['r']:g}": x["history"] for x in rows
                      if x["seed"] == cfg["seed0"] and "history" in x}
            if curves:
                path = fig_dir / "learning_curves.png"
                plots.save(plots.learning_curves(curves, title="torque cost per iteration (seed 0)"), path)
                out.append(path)
    elif exp == "keyframes":
        motions = keyframe_motions(body, cfg["gestures"], cfg["straight_reach"])
        tg = prepare(body, motions)
        sims = {}
        slsqp = next((x for x in rows if x["method"] == "slsqp"), None)
        if slsqp:
            sims["thesis SLSQP"] = _resimulate(body, slsqp["params"], tg, cfg)
        q = torch.full_like(tg.q, float("nan"))
        for j, name in enumerate(tg.names):
            run_dir = Path(cfg["out"]) / "pipeline" / name / "run"
            if (run_dir / "basis.json").exists():
                q[j] = _pipeline_q(body, cfg, run_dir, tg.select([j]))[0][0]
                out += _animations(run_dir, [name], fig_dir)
        sims["pipeline"] = q
        out += _sheets(body, tg, sims, fig_dir)
    elif exp == "filtering":
        motions = crude_motions(body)
        tg = prepare(body, motions)
        row = rows[-1]
        q = _resimulate(body, row["params"], tg, cfg)
        for j, m in enumerate(motions):
            k = len(m.t)
            path = fig_dir / f"{m.name}.png"
            plots.save(plots.stick_strip(body, {"input": m.q, "filtered": q[j, :k]},
                                         title=f"{m.name}: crude input vs played through the fields"),
                       path)
            path2 = fig_dir / f"{m.name}_hand.png"
            plots.save(plots.hand_paths(body, {"input": m.q, "filtered": q[j, :k]},
                                        title=f"{m.name}: hand path"), path2)
            out += [path, path2]
    return out


# --------------------------------------------------------------------------------- driver

RUNNERS = {"basin": basin, "shared": shared, "keyframes": keyframes, "filtering": filtering}


def run(cfg: dict) -> dict:
    """Run an experiment end to end: OUT/results.json, OUT/figures/*.png, OUT/tensorboard."""
    out = Path(cfg["out"])
    out.mkdir(parents=True, exist_ok=True)
    config_mod.dump(cfg, out / "config.yaml")
    t0 = time.perf_counter()
    result = RUNNERS[cfg["experiment"]](cfg)
    result.update(experiment=cfg["experiment"], quick=cfg["quick"], config=cfg,
                  elapsed_s=time.perf_counter() - t0)
    paths = figures(cfg, result)
    result["figures"] = [p.name for p in paths]
    (out / "results.json").write_text(json.dumps(result, indent=1, default=float))
    _log(cfg, result, paths)
    return result


def _log(cfg: dict, result: dict, paths: list) -> None:
    """Figures and success rates to OUT/tensorboard."""
    from torch.utils.tensorboard import SummaryWriter
    import matplotlib.image as mpimg
    with SummaryWriter(str(Path(cfg["out"]) / "tensorboard")) as w:
        for p in (p for p in paths if p.suffix == ".png"):
            w.add_image(f"figures/{p.stem}", mpimg.imread(p)[..., :3], dataformats="HWC")
        for group, ms in result["summary"].get("rates", {}).items():
            for method, v in ms.items():
                for r, rate in zip(v["r"], v["rate"]):
                    w.add_scalar(f"success/{group}/{method}", rate, int(round(100 * r)))


# ------------------------------------------------------------------------------- report

TITLES = {"basin": "1. The basin of the search (§4.1, figures 4-1 to 4-5)",
          "shared": "2. One basis for several motions (§4.2, figures 4-6 to 4-8)",
          "keyframes": "3. Motions not made by torque fields (§4.3, figure 4-9)",
          "filtering": "4. Motion filtering (§4.5.4)"}


def _pct(x: float) -> str:
    return f"{100 * x:.0f}%"


def _table(head: list, rows: list) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def goals(result: dict) -> list:
    """The issue's goals for this experiment, each as (text, met: bool)."""
    exp, s, out = result["experiment"], result["summary"], []
    if exp == "basin":
        for g, ms in s["r90"].items():
            lim = THESIS["basin"][g][0]
            if "local" in ms:
                out.append((f"{g}: local solver's 90%-success r = {ms['local']:g} ≥ 2 × thesis "
                            f"{lim:g} = {2 * lim:g}", ms["local"] >= 2 * lim))
            if "pipeline" in s["rates"][g]:
                rate = min(s["rates"][g]["pipeline"]["rate"])
                out.append((f"{g}: full pipeline 100% at every r (lowest {_pct(rate)})", rate == 1.0))
    elif exp == "shared":
        for g, ms in s["rates"].items():
            for m, v in ms.items():
                out.append((f"{m}: every motion reproduced at every r (lowest {_pct(min(v['rate']))})",
                            min(v["rate"]) == 1.0))
    elif exp == "keyframes":
        for method in dict.fromkeys(x["method"] for x in result["rows"]):
            rmse = [r for x in result["rows"] if x["method"] == method for r in x["rmse"]]
            out.append((f"{method}: every motion with joint RMSE ≤ 0.05 rad (worst {max(rmse):.3f} "
                        f"rad; {sum(r <= 0.05 for r in rmse)}/{len(rmse)} motions)", max(rmse) <= 0.05))
    return out


def text_summary(result: dict) -> str:
    """Markdown tables of an experiment's outcome and cost."""
    exp, s, parts = result["experiment"], result["summary"], []
    if exp in ("basin", "shared"):
        for g, ms in s["rates"].items():
            r = next(iter(ms.values()))["r"]
            rows = []
            for m, v in ms.items():
                if exp == "shared":
                    for name, rate in v["per_motion"].items():
                        rows.append([m, name] + [_pct(x) for x in rate] + [""])
                rows.append([m, "all" if exp == "shared" else g] + [_pct(x) for x in v["rate"]]
                            + [f"{s['r90'][g][m]:g}"])
            thesis = THESIS["basin"].get(g)
            title = f"**{g}** ({next(iter(ms.values()))['cases']} seeds per r" + (
                f"; thesis: recovered at r = {thesis[0]:g}, failed at r = {thesis[1]:g})" if thesis else ")")
            parts.append(title + "\n\n" + _table(["method", "motion"] + [f"r={x:g}" for x in r]
                                                 + ["90%-success r"], rows))
    elif exp == "keyframes":
        rows = []
        for row in result["rows"]:
            for k, name in enumerate(row["motions"]):
                rows.append([row["method"], name, f"{row['rmse'][k]:.4f}", f"{100 * row['tip'][k]:.2f}",
                             "yes" if row["rmse"][k] <= 0.05 else "no", row.get("M", 4)])
        parts.append(_table(["method", "motion", "joint RMSE (rad)", "tip error (cm)",
                             "RMSE ≤ 0.05", "M"], rows))
    elif exp == "filtering":
        base, row = result["rows"]
        parts.append(f"Basis learned on {', '.join(base['motions'])}: M = {base['M']}, all "
                     f"reproduced: {all(base['success'])}.")
        rows = [[name, f"{row['rmse'][k]:.4f}", f"{100 * row['tip'][k]:.1f}",
                 f"{100 * row['straightness_in'][k]:.1f}%",
                 f"{100 * row['straightness_out'][k]:.1f}%"]
                for k, name in enumerate(row["motions"])]
        parts.append(_table(["crude motion", "RMSE to input (rad)", "max tip distance to input (cm)",
                             "hand-path deviation from chord: input", "filtered"], rows))
    c = s["costs"]
    def ratio(x):
        return "-" if x is None else f"{x:.2f}"
    rows = [[m, v["runs"], f"{v['wall_s']:.1f}", ratio(v["wall_ratio"]), f"{v['wall_per_run_s']:.2f}",
             ratio(v["run_ratio"]), v["sims"], f"{v['sims_per_run']:.1f}"] for m, v in c.items()]
    parts.append("Cost (wall time of the fits, their own simulations included, not the final "
                 "check; a pipeline run serves every r):\n\n" + _table(
                     ["method", "runs", "wall (s)", "wall / SLSQP", "wall per run (s)",
                      "per run / SLSQP", "simulations", "simulations per run"], rows))
    g = goals(result)
    if g:
        parts.append("Goals:\n\n" + "\n".join(f"- {'met' if ok else '**not met**'}: {text}" for text, ok in g))
    return "\n\n".join(parts)


def report(runs="runs/experiments", out="docs/results.md") -> Path:
    """docs/results.md: for every experiment with a results.json under ``runs`` (the full
    size preferred over ``-quick``), the thesis' outcome, ours, the figures (copied next
    to the report) and the command that regenerates it."""
    import shutil
    from . import plots
    runs, out = Path(runs), Path(out)
    fig_root = out.parent / "results"
    fig_root.mkdir(parents=True, exist_ok=True)
    plots.save(plots.fields_gallery(arm()), fig_root / "fields.png")
    plots.save(plots.profiles_figure(), fig_root / "profiles.png")
    doc = ["# Results: the thesis' chapter 4, side by side", "",
           "Generated by `tflearn report` from the experiments' `results.json` files; every number "
           "below was measured by the command given with it. Success means the motion simulated "
           "from its initial state under the fitted torque program has joint RMSE ≤ 0.03 rad and "
           "hand-tip error ≤ 2 cm (experiment 3: joint RMSE ≤ 0.05 rad alone, the goal the issue sets; tip errors are reported).", "",
           "## The model", "",
           "Torque fields (thesis figure 3-1): torque in a 2-D slice of joint space and the hand "
           "force field it makes, for scalar, diagonal and full K.", "",
           "![fields](results/fields.png)", "",
           "Step ψ and pulse φ (thesis figure 3-2):", "", "![profiles](results/profiles.png)", ""]
    for exp in EXPERIMENTS:
        full, quick = runs / exp / "results.json", runs / f"{exp}-quick" / "results.json"
        src = full if full.exists() else quick if quick.exists() else None
        doc += [f"## {TITLES[exp]}", "", f"**Set-up:** {SETUP[exp]}", "",
                f"**Thesis:** {_thesis_text(exp)}", ""]
        if src is None:
            doc += ["Not run yet: `tflearn experiment " + exp + "`.", ""]
            continue
        result = json.loads(src.read_text())
        size = " (quick size)" if result["quick"] else ""
        compute = sum(v["wall_s"] for v in result["summary"]["costs"].values())
        doc += [f"**Ours**{size}: `tflearn experiment {exp}{' --quick' if result['quick'] else ''}` "
                f"(the fits took {compute / 60:.0f} min of single-threaded compute in all; cases "
                f"are cached, so a re-run only redraws).", "", text_summary(result), ""]
        dest = fig_root / exp
        dest.mkdir(exist_ok=True)
        for name in result["figures"]:
            shutil.copy(src.parent / "figures" / name, dest / name)
            doc += [f"![{Path(name).stem}](results/{exp}/{name})", ""]
    out.write_text("\n".join(doc))
    return out


SETUP = {
    "basin": "Each gesture alone, generated by simulation at 100 Hz. Every generating "
             "parameter (η, scalar k, a, b) times an independent factor in [1, r] is the "
             "initial guess (zeros stay zero). Methods: **slsqp** — the thesis' method, "
             "scipy SLSQP with numerical derivatives on the torque cost; **local** — "
             "tflearn's EM (exact NNLS weights + Levenberg–Marquardt on the fields; first "
             "with the weights the guess has at zero held there, then all free), then path "
             "matching through `odeint` when the torque fit is near (relative cost ≤ 1e-3) "
             "but not reproduced; **pipeline** — tflearn's full search (`train`), which "
             "ignores the guess, so its runs (one per seed) count at every r.",
    "shared": "Come-here, tuck and backwards reach together, one basis of four fields (their "
              "generating fields). slsqp and local start from the four generating fields and "
              "all weights noised by r; the pipeline learns four fields from no guess "
              "(`model.fields: 4`).",
    "keyframes": "Three-keyframe animations (postures of each gesture at its start, middle "
                 "and end; quintic spline, eased in and out) and a straight-line hand reach "
                 "(minimum-jerk timing, inverse kinematics of shoulder and elbow) — motions "
                 "no torque field made. The pipeline learns each motion's own basis with "
                 "learned onsets and durations (`model.phases: variable`), M found; the "
                 "baseline is the thesis' SLSQP on the torque cost from the four fields of "
                 "experiment 2, all motions together (as in figure 4-9).",
    "filtering": "A basis is learned on the gesture library by the pipeline; crude motions "
                 "(a straight-line hand reach, a two-keyframe move) are then fitted by their "
                 "weights alone (NNLS on the torques, then path matching of the weights) and "
                 "simulated. 'Deviation from chord' is the hand path's largest distance from "
                 "the straight line between its ends, relative to that line's length.",
}


def _thesis_text(exp: str) -> str:
    if exp == "basin":
        return "; ".join(f"{g} recovered at r = {a:g}, failed at r = {b:g}"
                         for g, (a, b) in THESIS["basin"].items()) + " (one trial per r)."
    return THESIS[exp]
