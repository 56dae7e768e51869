"""The chapter 4 experiments (``tflearn experiment NAME --quick``) and the report.

The quick sizes run end to end here; each asserts the experiment's success criterion on
at least one gesture. The numbers asserted are the ones docs/results.md reports for the
full sizes, where the quick size contains the same case (same gesture, r and seed)."""
from __future__ import annotations

import json
import re
from pathlib import Path
from typing import get_args

import pytest
import torch

from tflearn import cli, experiments
from tflearn.config import ConfigError
from tflearn.data import gestures
from tflearn.experiments import common
from tflearn.experiments.config import ExperimentConfig
from tflearn.model.program import model_from_state

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs" / "experiments"


def quick(name: str, tmp_path: Path, *overrides: str) -> dict:
    """Run ``tflearn experiment NAME --quick out=...`` in-process; its results.json."""
    out = tmp_path / name
    assert cli.main(["experiment", str(CONFIGS / f"{name}.yaml"), "--quick", f"out={out}",
                     *overrides]) == 0
    return json.loads((out / "results.json").read_text())


# ------------------------------------------------------------------------------- configs

def test_the_registry_covers_every_experiment():
    """Every experiment name the config accepts has a module providing the interface."""
    names = get_args(ExperimentConfig.model_fields["experiment"].annotation)
    assert set(experiments.EXPERIMENTS) == set(names)
    for name, module in experiments.EXPERIMENTS.items():
        for attr in ("run", "summary", "figures", "goals", "thesis"):
            assert callable(getattr(module, attr)), (name, attr)
        words = common.text(name)
        assert words["title"] and words["setup"] and module.thesis()


@pytest.mark.parametrize("name", experiments.EXPERIMENTS)
def test_every_experiment_has_a_config(name):
    cfg = experiments.load_config(CONFIGS / f"{name}.yaml")
    assert cfg.experiment == name and not cfg.quick
    assert not cfg.train.log.tensorboard and not cfg.train.log.progress
    q = experiments.load_config(CONFIGS / f"{name}.yaml", quick=True)
    assert q.quick and q.out.endswith("-quick")
    assert q.simulation.options().max_evals == q.simulation.max_evals


@pytest.mark.parametrize("text, message", [
    ("experiment: basin\nseedz: 3\n", "unknown config key 'seedz' (did you mean seeds"),
    ("experiment: basin\ngestures: [come_here, wave]\n", "'gestures': unknown gestures ['wave']"),
    ("experiment: nope\n", "'experiment' must be one of"),
    ("experiment: basin\nmethods: [slsqp, magic]\n", "'methods' must be one of"),
    ("experiment: basin\nsimulation: {budget: 100}\n", "unknown config key 'simulation.budget'"),
    ("experiment: basin\nquick: {r: fast}\n", "'quick.r' must be a list"),
    ("experiment: basin\nquick: {gestures: [wave]}\n", "'quick.gestures': unknown gestures"),
    ("experiment: basin\ntrain: {model: {stiffness: wobbly}}\n", "'train.model.stiffness' must be one of"),
])
def test_bad_experiment_config_names_file_and_key(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        experiments.load_config(path, quick=True)
    assert str(path) in str(err.value) and message in str(err.value)


def test_bad_override_names_file_and_key():
    with pytest.raises(ConfigError) as err:
        experiments.load_config(CONFIGS / "basin.yaml", overrides=["simulation.budget=5"])
    assert "basin.yaml" in str(err.value) and "'simulation.budget'" in str(err.value)
    cfg = experiments.load_config(CONFIGS / "basin.yaml", True, ["simulation.max_evals=5", "seeds=1"])
    assert cfg.simulation.max_evals == 5 and cfg.seeds == 1 and cfg.gestures == ["come_here"]


def test_only_the_pipeline_case_imports_train():
    """The package runs the pipeline through one function (common.fit_pipeline_case)."""
    package = ROOT / "tflearn" / "experiments"
    users = [p.name for p in package.glob("*.py") if re.search(r"\bimport train\b|tflearn\.train\b|"
                                                              r"from \.\.train\b", p.read_text())]
    assert users == ["common.py"]


def test_overrides_may_follow_options():
    """``tflearn experiment basin --quick seeds=5`` and ``train CFG --restart seed=3``:
    overrides after an option are still overrides; anything else is refused."""
    p = cli.build_parser()
    args = cli._parse(p, ["experiment", "basin", "--quick", "seeds=5", "jobs=1"])
    assert args.quick and args.overrides == ["seeds=5", "jobs=1"]
    args = cli._parse(p, ["train", "c.yaml", "seed=1", "--restart", "out=x"])
    assert args.restart and args.overrides == ["seed=1", "out=x"]
    with pytest.raises(SystemExit):
        cli._parse(p, ["experiment", "basin", "--quick", "--fast"])


# -------------------------------------------------------------------------- noise model

def test_noise_multiplies_each_parameter_by_a_factor_in_1_r():
    true = common.generating([gestures.GESTURES["planar_line"]])
    u = common.noise_draws(true, seed=3, salt=3)
    assert common.noise_draws(true, seed=3, salt=3)["eta"].equal(u["eta"])   # seeded
    for r in (1.0, 2.6, 10.0):
        guess = common.noised(true, u, r)
        for key in true:
            t, g = true[key], guess[key]
            assert bool((g[t == 0] == 0).all())                    # zeros stay zero
            ratio = g[t != 0] / t[t != 0]
            assert float(ratio.min()) >= 1 - 1e-15 and float(ratio.max()) <= r + 1e-12
    big = common.noised(true, u, 10.0)["k"] / true["k"]
    assert torch.allclose(big, 1 + 9 * u["k"])


def test_r90_is_the_last_r_of_the_leading_run_above_90_percent():
    assert common.r90([1.2, 2, 3, 4], [1.0, 0.95, 0.85, 1.0]) == 2
    assert common.r90([1.2, 2], [0.5, 1.0]) == 0.0


# -------------------------------------------------------------------- the quick versions

@pytest.mark.slow
def test_basin_quick(tmp_path):
    """come_here at r = 3.0, where the thesis' SLSQP stopped with no motion: tflearn's
    local solver (EM) and its pipeline reproduce it."""
    res = quick("basin", tmp_path, "seeds=1")
    rates = res["summary"]["rates"]["come_here"]
    i = rates["local"]["r"].index(3.0)
    assert rates["local"]["rate"][i] == 1.0 and rates["pipeline"]["rate"][i] == 1.0
    assert rates["slsqp"]["rate"][rates["slsqp"]["r"].index(1.4)] == 1.0
    local = [x for x in res["rows"] if x["method"] == "local"]
    assert all(x["rmse"][0] <= 0.03 and x["tip"][0] <= 0.02 for x in local)
    assert res["summary"]["costs"]["slsqp"]["wall_ratio"] == 1.0
    assert {"success_vs_r.png", "come_here.png"} <= set(res["figures"])
    assert all((tmp_path / "basin" / "figures" / f).exists() for f in res["figures"])


def test_local_solver_starts_wide():
    """come_here from the guess of r = 4.2, seed 0 (the full sweep's case): started at the
    guessed stiffnesses, EM ends with no torque at all (relative cost 1.0: the far, stiff
    field's Gaussian vanishes along the motion, so its NNLS weight and gradient are 0);
    started at a tenth of them (``local.start_wide``, the default) it reproduces the
    gesture (measured: cost 7.8e-11)."""
    cfg = experiments.load_config(CONFIGS / "basin.yaml", overrides=["gestures=[come_here]"])
    common.setup(cfg, {"come_here": ["come_here"]})
    _, _, tg, true, salt = common._STATE["groups"]["come_here"]
    body = common._STATE["body"]
    guess = common.noised(true, common.noise_draws(true, 0, salt), 4.2)
    as_guessed = experiments.load_config(CONFIGS / "basin.yaml", overrides=["local.start_wide=1"])
    narrow = common.fit_local_case(body, guess, tg, as_guessed)
    wide = common.fit_local_case(body, guess, tg, cfg)
    ok = lambda fit: all(common.check(body, fit["basis"], fit["weights"], tg, cfg)["success"])
    assert narrow["cost"] > 0.99 and not ok(narrow)
    assert wide["cost"] < 1e-9 and ok(wide)


@pytest.mark.slow
def test_shared_quick(tmp_path):
    """Four shared fields for come-here, tuck and backwards reach from r = 1.4: every
    motion reproduced by the local solver."""
    res = quick("shared", tmp_path)
    row = next(x for x in res["rows"] if x["method"] == "local")
    assert row["motions"] == ["come_here", "tuck", "backwards_reach"]
    assert all(row["success"]) and len(row["model"]["basis"]["eta"]) == 4
    basis, weights = model_from_state(row["model"])          # the one model serialiser
    assert basis.M == 4 and weights.names == row["motions"]
    assert max(row["rmse"]) <= 0.03 and max(row["tip"]) <= 0.02


@pytest.mark.slow
def test_keyframes_quick(tmp_path):
    """A three-keyframe spline resembling the come-here (not made by fields): the
    pipeline's own basis, damped fields with two sub-movement windows, reproduces it
    within the bar of field-generated motions (≤ 0.03 rad, ≤ 2 cm; measured in the full
    experiment: 0.0094 rad, 1.3 cm, M = 3), while the thesis' SLSQP from the four
    fields of §4.2 loses it, as in thesis figure 4-9. (The quick size leaves out the
    spanning layout: its quick run is experiment 5's, below.)"""
    res = quick("keyframes", tmp_path)
    pipe = next(x for x in res["rows"] if x["method"] == "pipeline")
    slsqp = next(x for x in res["rows"] if x["method"] == "slsqp")
    assert pipe["motions"] == slsqp["motions"] == ["come_here_keys"]
    assert pipe["rmse"][0] <= 0.03 and pipe["tip"][0] <= 0.02 and pipe["success"] == [True]
    assert slsqp["rmse"][0] > 0.05 and slsqp["success"] == [False]
    assert 1 <= pipe["M"] <= 4 and [x["method"] for x in res["rows"]] == ["slsqp", "pipeline"]


@pytest.mark.slow
def test_filtering_quick(tmp_path):
    """Crude motions played through a basis learned on come_here and the stiff-elbow
    lift: the basis reproduces its own gestures (the success criterion), the crude
    straight reach is straight, and its weights-only fit is simulated to a finite path
    whose figures are drawn."""
    res = quick("filtering", tmp_path)
    base, row = res["rows"]
    assert base["motions"] == ["come_here", "stiff_elbow_lift"] and all(base["success"])
    k = row["motions"].index("straight_reach")
    assert row["straightness_in"][k] < 1e-3      # straight to the IK's 1 mm tolerance
    assert all(x is not None and x == x for x in row["straightness_out"])
    assert all(r < float("inf") for r in row["rmse"])
    assert {"straight_reach.png", "straight_reach_hand.png"} <= set(res["figures"])


@pytest.mark.slow
def test_reaches_quick_layout(tmp_path):
    """Experiment 5's quick size by the spanning layout: eight fields laid out around
    the two training reaches (no search) reproduce both within the bar (measured: 0.0073
    rad, 0.2 cm at worst), and the held-out reach played through that frozen basis comes
    back within the 0.05 rad goal (measured: 0.0037 rad); its figures are drawn."""
    res = quick("reaches", tmp_path, "methods=[layout]")
    base, row = res["rows"]
    assert (base["method"], row["method"]) == ("layout", "layout, held out")
    assert base["M"] == 8 and all(base["success"])
    assert max(base["rmse"]) <= 0.03 and max(base["tip"]) <= 0.02
    assert row["motions"] == ["held_out_reach"] and row["rmse"][0] <= 0.05
    assert row["straightness_in"][0] < 1e-3 and row["straightness_out"][0] < 0.05
    assert {"held_out_reach_hand.png", "reach_0.7_-0.2.png"} <= set(res["figures"])


def test_filtered_table_marks_a_path_not_simulated():
    """A held-out motion whose simulation failed (RMSE ∞, deviation NaN) reads "–" in the
    filtered column, not "nan%"; a simulated one its deviation in %."""
    from tflearn.experiments import filtering
    inf, nan = float("inf"), float("nan")
    row = {"motions": ["held", "ok"], "rmse": [inf, 0.01], "tip": [inf, 0.002],
           "straightness_in": [0.0, 0.001], "straightness_out": [nan, 0.0123]}
    lines = filtering.filtered_table(row, "held-out motion").splitlines()
    assert lines[2] == "| held | inf | inf | 0.0% | – |"
    assert lines[3] == "| ok | 0.0100 | 0.2 | 0.1% | 1.2% |"


@pytest.mark.slow
def test_reach_class_is_straight_and_spread():
    """The reach class of experiment 5: eight straight-line reaches from rest (hand paths
    straight to the IK's 1 mm) to distinct targets, and a held-out one inside the class
    (between its turns and its distances); its goal line reads as the others."""
    import math

    from tflearn.experiments import filtering, reaches
    from tflearn.experiments.reporting import goal_line
    from tflearn.physics import dynamics
    from tflearn.physics.body import arm
    body = arm()
    train, held = reaches.reach_class(body)
    assert len(train) == 8 and held.name == "held_out_reach"
    ends = [dynamics.tip_position(body, m.q[-1]) for m in train + [held]]
    start = dynamics.tip_position(body, train[0].q[0])
    for m in train + [held]:
        assert filtering.straightness(body, m.q) < 1e-3
        assert float(m.t[-1]) == reaches.DURATION
    gaps = [float((a - b).norm()) for i, a in enumerate(ends) for b in ends[i + 1:]]
    assert min(gaps) > 0.05
    dist = [float((e - start).norm()) for e in ends]
    assert min(dist[:8]) < dist[8] < max(dist[:8])
    turn = [math.atan2(float(e[0]), -float(e[1])) for e in ends]
    assert min(turn[:8]) < turn[8] < max(turn[:8])
    rows = [{"method": "layout", "motions": ["a", "b"], "M": 5, "success": [True, False],
             "rmse": [0.01, 0.07], "tip": [0.005, 0.09]},
            {"method": "layout, held out", "motions": ["held_out_reach"], "rmse": [0.04],
             "tip": [0.098], "straightness_in": [0.0004], "straightness_out": [0.09]}]
    lines = [goal_line(*g) for g in reaches.goals({"rows": rows})]
    assert lines == [
        "- goal: layout: every reach of the class with joint RMSE ≤ 0.03 rad and tip error "
        "≤ 2 cm; measured: 1 of 2 within it; the worst RMSE 0.070 rad, the worst tip error "
        "9.0 cm — **not met**",
        "- goal: layout: the held-out reach, played through the class's frozen basis, within "
        "0.05 rad joint RMSE of its input; measured: 0.040 rad — met"]
    text = reaches.summary({"rows": rows})
    assert text.startswith("**layout**: basis learned on 2 reaches: M = 5, 1 of 2 reproduced "
                           "(the worst, b: 0.0700 rad, 9.0 cm).")
    assert "| held_out_reach | 0.0400 | 9.8 | 0.0% | 9.0% |" in text


def test_reaches_layout_config():
    """Experiment 5's layout method trains with ``train`` ← ``layout`` and solver.method
    layout; the pipeline with ``train``; a bad key under ``layout`` is refused naming it,
    and each experiment refuses a method it does not run."""
    from tflearn.experiments import load_config
    cfg = load_config(CONFIGS / "reaches.yaml", quick=True)
    assert cfg.methods == ["pipeline", "layout"]
    pipe, lay = cfg.training("pipeline"), cfg.training("layout")
    assert (pipe.solver.method, pipe.model.windows, pipe.solver.ridge) == ("pipeline", 2, 0.0)
    assert (lay.solver.method, lay.model.windows, lay.solver.ridge) == ("layout", 8, 1e-4)
    assert (lay.solver.layout.shape, lay.model.field_damping) == ("simplex", 0.2)
    assert (pipe.solver.path.steps, lay.solver.path.steps) == (2, 0)       # quick's, layout's
    with pytest.raises(ConfigError, match=r"config key 'layout': unknown config key "
                                          r"'solver\.layot' \(did you mean layout\?\)"):
        load_config(CONFIGS / "reaches.yaml",
                    overrides=["layout.solver.layot.shape=simplex"])
    with pytest.raises(ConfigError, match="'methods': basin runs slsqp, local, pipeline, not layout"):
        load_config(CONFIGS / "basin.yaml", overrides=["methods=[layout]"])
    assert load_config(CONFIGS / "filtering.yaml",
                       overrides=["methods=[pipeline]"]).methods == ["pipeline"]


@pytest.mark.slow
def test_report_from_quick_results(tmp_path):
    """``tflearn report`` writes every experiment's section, its figures and the model figures."""
    runs = tmp_path / "runs"
    quick("basin", runs, "seeds=1", "r=[3.0]", "methods=[slsqp,local]")
    (runs / "basin").rename(runs / "basin-quick")
    out = tmp_path / "docs" / "results.md"
    assert cli.main(["report", "--runs", str(runs), "--out", str(out)]) == 0
    text = out.read_text()
    for name in experiments.EXPERIMENTS:
        assert f"## {common.text(name)['title']}" in text
    assert "(quick size)" in text and "recovered at r = 2.6, failed at r = 3" in text
    assert text.count("Not run yet") == len(experiments.EXPERIMENTS) - 1
    for ref in ("results/fields.png", "results/profiles.png", "results/basin/success_vs_r.png"):
        assert f"]({ref})" in text and (out.parent / ref).exists()
    assert "[history.md](history.md#results)" in text and not COMMIT.search(text)


# a commit hash: 7 to 40 hex digits with a letter and a digit (docs/history.md alone keeps them)
COMMIT = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")


def test_report_words_are_current():
    """The report's words (text.yaml) state current figures: no commit hashes, the
    history of re-measurements linked instead."""
    words = (ROOT / "tflearn" / "experiments" / "text.yaml").read_text()
    assert not COMMIT.search(words), COMMIT.search(words)
    assert "history.md" in common.text("report")["intro"]


def test_goal_lines_read_as_goal_measured_verdict():
    """Each goal reads "goal: X; measured: Y — met / not met", with no inequality that
    contradicts its verdict (docs/results.md)."""
    from tflearn.experiments import basin, keyframes, shared
    from tflearn.experiments.reporting import goal_line
    result = {"summary": {"r90": {"come_here": {"local": 3.0}, "tuck": {"local": 0.0}},
                          "rates": {"come_here": {"local": {"r": [1.0, 3.0, 4.0], "rate": [1, 1, 0.5]},
                                                  "pipeline": {"r": [1.0], "rate": [1.0]}},
                                    "tuck": {"local": {"r": [1.4, 2.0], "rate": [0.5, 0.0]}}}}}
    lines = [goal_line(*g) for g in basin.goals(result)]
    assert lines == [
        "- goal: come_here: the local solver succeeds at least 90% of the time up to r ≥ 5.2 "
        "(twice the thesis' 2.6); measured: at least 90% up to r = 3 — **not met**",
        "- goal: come_here: the full pipeline reproduces the gesture every time, at every r; "
        "measured: lowest success rate 100% — met",
        "- goal: tuck: the local solver succeeds at least 90% of the time up to r ≥ 7.6 "
        "(twice the thesis' 3.8); measured: below 90% already at r = 1.4 — **not met**"]
    line, = (goal_line(*g) for g in shared.goals(
        {"summary": {"rates": {"a+b": {"local": {"rate": [1.0, 0.5]}}}}}))
    assert line == ("- goal: local: every motion reproduced every time, at every r; "
                    "measured: lowest success rate 50% — **not met**")
    line, = (goal_line(*g) for g in keyframes.goals(
        {"rows": [{"method": "pipeline", "rmse": [0.01, 0.02], "tip": [0.005, 0.019]}]}))
    assert line == ("- goal: pipeline: every motion with joint RMSE ≤ 0.03 rad and tip error ≤ 2 cm; "
                    "measured: 2 of 2 motions within it; the worst RMSE 0.020 rad, the worst tip "
                    "error 1.9 cm — met")
    line, = (goal_line(*g) for g in keyframes.goals(
        {"rows": [{"method": "pipeline", "rmse": [0.01, 0.02], "tip": [0.005, 0.021]}]}))
    assert line.endswith("1 of 2 motions within it; the worst RMSE 0.020 rad, the worst tip "
                         "error 2.1 cm — **not met**")


def test_config_names_the_gesture_library_and_needs_no_torch():
    """The experiment config checks gesture names against the library without importing
    torch (so a bad config is refused at once)."""
    import subprocess
    import sys

    from tflearn.data import gestures
    from tflearn.experiments import config as exp_config
    assert exp_config.GESTURES == tuple(gestures.GESTURES)
    code = ("import sys; from tflearn.experiments import load_config; "
            "load_config('configs/experiments/basin.yaml'); print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=ROOT)
    assert out.stdout.strip() == "False"
