"""``solver.method: auto`` (tflearn.train.choice): the pipeline for motions a few fields
made, convergent pairs for motion none made, decided from the motions' torques.

The probe's relative torque costs on field-made gestures and on eased keyframe splines
lie orders of magnitude apart; the decision follows the majority of the probed motions;
the convergent settings it takes are configs/convergent.yaml's; and the default config
trains keyframed motion into a convergent basis that reproduces it.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from tflearn import config, train
from tflearn.data import gestures
from tflearn.data.keyframes import random_keyframes
from tflearn.fit import targets
from tflearn.log import method_line
from tflearn.motions.motion import save
from tflearn.physics import body as tb
from tflearn.train.choice import choose, probed

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
DIAG = "model.stiffness=diag"     # given: the kind is not probed again with full K (tests of other things)


@pytest.fixture(scope="module")
def motions():
    """{name: Motion}: two gestures a field made and two eased keyframe animations."""
    body = tb.arm()
    made = {m.name: m for m, _ in gestures.generate(body, gestures=[gestures.GESTURES[n]
                                                                     for n in ("come_here", "tuck")])}
    keys = {m.name: m for m in random_keyframes(body, 2, seed=11)}
    return body, {**made, **keys}


def _targets(body, motions, names):
    return targets.prepare(body, [motions[n] for n in names])


@pytest.mark.slow
def test_probe_tells_field_made_motion_from_keyframes(motions):
    """A field-made gesture's torques on a few fields are exact to 1e-6; a keyframe
    spline's stay above 5e-3 (the bar is 2e-3)."""
    body, ms = motions
    cfg = config.load(CONFIGS / "gestures.yaml", ["solver.auto.probes=4"])
    costs = probed(cfg, body, _targets(body, ms, list(ms)))
    assert set(costs) == set(ms)
    assert costs["come_here"] < 1e-6 and costs["tuck"] < 1e-6
    assert costs["keys11_0"] > 5e-3 and costs["keys11_1"] > 5e-3


@pytest.mark.parametrize("names, method", [
    (["come_here", "tuck", "keys11_0"], "pipeline"),
    (["come_here", "keys11_0", "keys11_1"], "convergent"),
])
def test_the_majority_of_the_probes_decides(motions, names, method):
    """Three probes: two field-made of three give the pipeline, one of three the
    convergent pairs; the decision names every probed motion's cost."""
    body, ms = motions
    cfg = config.load(CONFIGS / "gestures.yaml", [DIAG])
    chosen, decision = choose(cfg, body, _targets(body, ms, names))
    assert decision["method"] == method and list(decision["probes"]) == ["diag"]
    assert list(decision["probes"]["diag"]) == names
    assert decision["stiffness"] == ("diag" if method == "pipeline" else None)
    assert chosen.solver.method == ("pipeline" if method == "pipeline" else "layout")
    if method == "pipeline":                                 # nothing else changes
        assert chosen.model_dump() == cfg.replace(solver={"method": "pipeline"}).model_dump()


@pytest.mark.slow
def test_a_kind_no_better_leaves_the_runs_own(motions):
    """A probe beyond the bar (a keyframe spline among two gestures) has the probes
    searched again with full K; full brings no more of them within it, so the run's
    own kind (diag) is learned, nothing else changed."""
    body, ms = motions
    names = ["come_here", "tuck", "keys11_0"]
    cfg = config.load(CONFIGS / "gestures.yaml")
    chosen, decision = choose(cfg, body, _targets(body, ms, names))
    assert list(decision["probes"]) == ["diag", "full"]
    assert all(list(costs) == names for costs in decision["probes"].values())
    assert (decision["method"], decision["stiffness"]) == ("pipeline", "diag")
    assert chosen.model_dump() == cfg.replace(solver={"method": "pipeline"}).model_dump()


def test_convergent_choice_is_configs_convergent(motions):
    """The settings auto takes for keyframes are configs/convergent.yaml's, key for key
    (but data, out and log); any method but auto is left as it is."""
    body, ms = motions
    tg = _targets(body, ms, ["keys11_0"])
    chosen, _ = choose(config.load(CONFIGS / "gestures.yaml", [DIAG]), body, tg)
    want = config.load(CONFIGS / "convergent.yaml").model_dump()
    got = chosen.model_dump()
    for key in ("data", "out", "log"):
        got.pop(key), want.pop(key)
    assert got == want
    cfg = config.load(CONFIGS / "gestures.yaml", ["solver.method=pipeline"])
    assert choose(cfg, body, tg) == (cfg, None)


def test_convergent_choice_keeps_the_command_lines_keys(motions):
    """Keys given on the command line stay when auto takes the convergent settings (a
    section named in part keeps its other keys from configs/convergent.yaml); the
    config file's keys are replaced."""
    body, ms = motions
    tg = _targets(body, ms, ["keys11_0"])
    given = ["solver.shooting.receding=null", "solver.layout.radius=1.5", "solver.path.max_evals=30000", DIAG]
    chosen, decision = choose(config.load(CONFIGS / "gestures.yaml", given), body, tg)
    assert decision["method"] == "convergent"
    assert chosen.solver.shooting.receding is None and chosen.solver.path.max_evals == 30000
    assert chosen.solver.layout.radius == 1.5 and chosen.solver.layout.shape == "pairs"
    assert chosen.solver.shooting.tip_weight == config.CONVERGENT["solver"]["shooting"]["tip_weight"]
    assert chosen.solver.path.rtol == config.CONVERGENT["solver"]["path"]["rtol"]
    assert chosen.model.windows == config.CONVERGENT["model"]["windows"]
    assert chosen.given == {"solver": {"shooting": {"receding": None}, "layout": {"radius": 1.5},
                                       "path": {"max_evals": 30000}}, "model": {"stiffness": "diag"}}


def test_an_earlier_decision_is_applied_without_probing(motions, monkeypatch):
    """``choose(..., earlier)``, a resumed run's decision: applied as it is, nothing
    probed; the config is the one the same decision taken afresh gives."""
    body, ms = motions
    tg = _targets(body, ms, ["keys11_0"])
    cfg = config.load(CONFIGS / "gestures.yaml", ["solver.layout.radius=1.5", DIAG])
    fresh, decision = choose(cfg, body, tg)
    monkeypatch.setattr("tflearn.train.choice.probed", lambda *a: pytest.fail("probed"))
    again, same = choose(cfg, body, tg, decision)
    assert same is decision and again == fresh and again.solver.layout.radius == 1.5
    piped, _ = choose(cfg, body, tg, {**decision, "method": "pipeline", "stiffness": "full"})
    assert piped == cfg.replace(solver={"method": "pipeline"}, model={"stiffness": "full"})
    old = {"method": "pipeline", "tol": 2e-3, "probes": {"keys11_0": 1e-4}}   # before the kind was decided
    piped, kept = choose(cfg, body, tg, old)
    assert piped == cfg.replace(solver={"method": "pipeline"})
    assert kept == {**old, "stiffness": "diag", "probes": {"diag": old["probes"]}}


@pytest.fixture(scope="module")
def full_made():
    """Three motions of random programs with full symmetric K (seed 3: diag fields
    explain one of them within the bar)."""
    body = tb.arm()
    programs = gestures.random_gestures(3, seed=3, stiffness="full")
    return body, targets.prepare(body, [m for m, _ in gestures.generate_resolved(programs)])


@pytest.mark.slow
def test_motions_made_with_full_stiffness_get_full_fields(full_made):
    """Motions made by fields with full K: a few diag fields leave most of them beyond
    the bar, a few full fields bring all three within it, and the pipeline learns full
    K; given on the command line, the kind is kept (and the pairs taken)."""
    body, tg = full_made
    cfg = config.load(CONFIGS / "gestures.yaml")
    chosen, decision = choose(cfg, body, tg)
    tol = cfg.solver.auto.tol
    assert sum(c <= tol for c in decision["probes"]["diag"].values()) <= 1
    assert all(c <= tol for c in decision["probes"]["full"].values())
    assert (decision["method"], decision["stiffness"]) == ("pipeline", "full")
    assert chosen == cfg.replace(solver={"method": "pipeline"}, model={"stiffness": "full"})
    line = method_line(decision)
    low = min(decision["probes"]["full"].values())
    assert line.startswith("method: the pipeline learned the shared basis, full K")
    assert f"full {low:.1e}–" in line and "diag " in line
    given = config.load(CONFIGS / "gestures.yaml", ["model.stiffness=diag"])
    chosen, decision = choose(given, body, tg)
    assert list(decision["probes"]) == ["diag"] and decision["method"] == "convergent"
    assert chosen.model.stiffness == "diag" and chosen.solver.method == "layout"


@pytest.mark.slow
def test_default_train_holds_keyframes_with_convergent_fields(motions, tmp_path):
    """``train configs/gestures.yaml data=DIR`` on two keyframe animations: convergent
    pairs chosen, both reproduced (≤ 0.03 rad, ≤ 2 cm), every centre a posture (each
    joint block's angle < π), the choice in metrics.json and config.yaml; run again,
    the finished run keeps it, taken from its checkpoint without probing again."""
    body, ms = motions
    data = tmp_path / "keys"
    data.mkdir()
    for name in ("keys11_0", "keys11_1"):
        save(ms[name], data / f"{name}.npz")
    cfg = config.load(CONFIGS / "gestures.yaml", [f"data={data}", f"out={tmp_path / 'run'}",
                                                  "log.tensorboard=false"])
    metrics = train.run(cfg, progress=False)
    assert metrics["history"]["method"]["method"] == "convergent"
    assert all(m["success"] and m["rmse"] <= 0.03 and m["tip"] <= 0.02 for m in metrics["motions"].values())
    basis = json.loads((tmp_path / "run" / "basis.json").read_text())
    eta = torch.tensor([f["eta"] for f in basis["fields"]], dtype=torch.float64)
    assert eta.shape[0] == 2 * body.nv
    assert all(float(eta[:, body.slice(i)].norm(dim=-1).max()) < math.pi for i in range(len(body.links)))
    assert config.load(tmp_path / "run" / "config.yaml").solver.method == "layout"
    with pytest.MonkeyPatch.context() as patch:                 # the decision is the checkpoint's
        patch.setattr("tflearn.train.choice.probed", lambda *a: pytest.fail("probed again"))
        again = train.run(cfg, progress=False)
    assert again["history"]["method"] == metrics["history"]["method"]
    assert again["motions"] == metrics["motions"]
