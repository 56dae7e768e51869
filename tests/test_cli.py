"""The command line, called in-process: ``tflearn gestures|evaluate|simulate`` and ``train``."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tflearn import cli, config
from tflearn.data import gestures
from tflearn.io import basis as bio

from test_learning import small_run

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return small_run(tmp_path_factory)       # the run shared with test_learning.py


def rotation_distance(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Per sample, the largest joint-rotation angle between two arm paths (T×7 each):
    |log(R1ᵀR2)| for the ball joints and the hinge angle difference (T×3)."""
    from scipy.spatial.transform import Rotation
    out = []
    for s in (slice(0, 3), slice(4, 7)):
        r = Rotation.from_rotvec(q1[:, s]).inv() * Rotation.from_rotvec(q2[:, s])
        out.append(np.linalg.norm(r.as_rotvec(), axis=-1))
    out.append(np.abs(q1[:, 3] - q2[:, 3]))
    return np.stack(out, -1)


def test_gestures_and_simulate(tmp_path, capsys):
    """``tflearn gestures --no-plots`` writes 5 npz + 5 json; each json loads and holds its
    gesture's program, and ``tflearn simulate`` of it reproduces its npz: over the whole
    3 s for planar_line, over the first 0.5 s (``--duration 0.5``) for the others, whose
    full-length replays at rtol 1e-9 cost 10-60 s each on the test machine (measured
    agreement: joint angles ≤ 2.3e-8 rad, velocities ≤ 1.3e-6 rad/s over full lengths)."""
    out = tmp_path / "lib"
    assert cli.main(["gestures", "--out", str(out), "--no-plots"]) == 0
    names = sorted(gestures.GESTURES)
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"{n}.npz" for n in names] + [f"{n}.json" for n in names])
    printed = capsys.readouterr().out
    assert "wrote 5 gestures" in printed and all(f"{n}.json" in printed for n in names)
    for name in names:
        lb = bio.load(out / f"{name}.json")
        g = gestures.GESTURES[name]
        assert lb.names == [name] and float(lb.rate[0]) == 100.0
        assert float(lb.weights.duration[0]) == g.duration
        assert lb.basis.M == len(g.eta)
        np.testing.assert_allclose(lb.basis.eta.detach().numpy(), np.array(g.eta), rtol=0, atol=0)
        np.testing.assert_allclose(lb.basis.K().detach().numpy(),
                                   np.array([k * np.eye(7) for k in g.k]), rtol=0, atol=1e-15)
        np.testing.assert_allclose(lb.weights.a.detach().numpy()[0], g.a, rtol=0, atol=0)
        np.testing.assert_allclose(lb.weights.b.detach().numpy()[0], g.b, rtol=0, atol=0)
        ref = np.load(out / f"{name}.npz")
        assert ref["q"].shape == (int(round(100 * g.duration)) + 1, 7)
        full = name == "planar_line"
        sim_path = tmp_path / "sim" / f"{name}.npz"
        argv = ["simulate", str(out / f"{name}.json"), "--motion", name, "--out", str(sim_path)]
        assert cli.main(argv if full else argv + ["--duration", "0.5"]) == 0
        assert capsys.readouterr().out.strip().splitlines()[-1] == f"wrote {sim_path}"
        sim = np.load(sim_path)
        T = len(sim["t"])
        assert T == (len(ref["t"]) if full else 51)
        assert np.abs(sim["t"] - ref["t"][:T]).max() <= 1e-12
        assert rotation_distance(sim["q"], ref["q"][:T]).max() <= 1e-6, name
        assert np.abs(sim["qd"] - ref["qd"][:T]).max() <= 1e-6 * max(1.0, np.abs(ref["qd"]).max()), name


def test_simulate_errors(tmp_path, capsys):
    import torch

    from tflearn.physics.body import arm
    basis, weights, _ = gestures.library_model([gestures.GESTURES["tuck"]])
    z = torch.zeros(1, 7, dtype=torch.float64)
    bio.save(bio.LearnedBasis(arm(), basis, weights, z, z, torch.tensor([100.0], dtype=torch.float64)),
             tmp_path / "tuck.json")
    assert cli.main(["simulate", str(tmp_path / "tuck.json"), "--motion", "wave",
                     "--out", str(tmp_path / "x.npz")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tflearn: {tmp_path / 'tuck.json'}: no motion named 'wave'")
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.npz").exists()
    (tmp_path / "bad.json").write_text("{}")
    assert cli.main(["simulate", str(tmp_path / "bad.json"), "--motion", "tuck",
                     "--out", str(tmp_path / "x.npz")]) == 2
    assert str(tmp_path / "bad.json") in capsys.readouterr().err
    # --rate and --duration change the sampling
    out = tmp_path / "short.npz"
    assert cli.main(["simulate", str(tmp_path / "tuck.json"), "--motion", "tuck", "--out", str(out),
                     "--rate", "10", "--duration", "0.5"]) == 0
    t = np.load(out)["t"]
    np.testing.assert_allclose(t, np.arange(6) / 10.0, rtol=0, atol=1e-15)


@pytest.mark.parametrize("entry", ["train", "tflearn"])
@pytest.mark.parametrize("override,key", [
    ("solver.em.stepz=3", "solver.em.stepz"),
    ("nonsense=1", "nonsense"),
    ("solver.path.steps=-1", "solver.path.steps"),
])
def test_train_refuses_bad_override_before_work(tmp_path, capsys, entry, override, key):
    out = tmp_path / "never"
    argv = [str(ROOT / "configs" / "gestures.yaml"), f"out={out}", override, "log.progress=false"]
    code = cli.train_main(argv) if entry == "train" else cli.main(["train", *argv])
    assert code == 2
    err = capsys.readouterr().err
    prog = "train" if entry == "train" else "tflearn"
    assert err.startswith(f"{prog}: ") and repr(key) in err
    assert not out.exists()


def test_train_missing_config_file(tmp_path, capsys):
    missing = tmp_path / "nope.yaml"
    assert cli.train_main([str(missing), f"out={tmp_path / 'x'}"]) == 2
    assert str(missing) in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_evaluate_run(run_dir, capsys):
    """``tflearn evaluate RUN`` re-simulates the run's basis.json on its data: the same
    figures as metrics.json (measured equal to ~1e-9)."""
    run = run_dir["out"]
    assert cli.main(["evaluate", str(run)]) == 0
    printed = capsys.readouterr().out
    ev = json.loads((run / "evaluation.json").read_text())
    ref = json.loads((run / "metrics.json").read_text())
    assert sorted(ev["motions"]) == sorted(ref["motions"])
    for name, row in ref["motions"].items():
        e = ev["motions"][name]
        assert e["synthesized"] is False and e["success"] == row["success"]
        for key in ("rmse", "tip", "torque_rel_rms"):
            assert abs(e[key] - row[key]) <= 1e-6 * max(1.0, abs(row[key])), (name, key)
        assert name in printed
    assert ev["overall"]["M"] == ref["overall"]["M"]
    assert ev["overall"]["success"] == ref["overall"]["success"]
    cfg = config.load(run / "config.yaml").solver.path              # the run's own simulation settings
    assert ev["simulation"] == {"method": cfg.method, "rtol": cfg.rtol, "atol": cfg.atol,
                                "max_evals": cfg.max_evals}
    assert abs(ev["overall"]["tip"] - ref["overall"]["tip"]) <= 1e-6
    # overall.rmse is over all samples, as in metrics.json
    # (see test_evaluate_overall_rmse_matches_metrics).
    assert printed.strip().splitlines()[-1] == f"wrote {run / 'evaluation.json'}"


@pytest.mark.slow
def test_evaluate_at_tighter_tolerances(run_dir, tmp_path, capsys):
    """``--rtol``, ``--atol`` and ``--max-evals`` re-simulate the run at other settings,
    which evaluation.json records (without them the run's, test_evaluate_run): the small
    run's reproductions are converged — the same successes, every RMSE within 1e-4 rad of the
    run's tolerance's; a tolerance that is not a positive number is refused."""
    run, out = run_dir["out"], tmp_path / "tight.json"
    assert cli.main(["evaluate", str(run), "--out", str(out), "--rtol", "1e-9", "--atol", "1e-11",
                     "--max-evals", "200000", "--quiet"]) == 0
    tight, ref = json.loads(out.read_text()), json.loads((run / "metrics.json").read_text())
    cfg = config.load(run / "config.yaml").solver.path
    assert tight["simulation"] == {"method": cfg.method, "rtol": 1e-9, "atol": 1e-11, "max_evals": 200000}
    assert cfg.rtol > 1e-9
    for name, row in ref["motions"].items():
        assert tight["motions"][name]["success"] == row["success"]
        assert abs(tight["motions"][name]["rmse"] - row["rmse"]) < 1e-4, name
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        cli.main(["evaluate", str(run), "--rtol", "0"])
    assert exit_.value.code == 2 and "must be a positive number, got 0" in capsys.readouterr().err


@pytest.mark.slow
def test_evaluate_overall_rmse_matches_metrics(run_dir, tmp_path):
    from tflearn import evaluate
    ev = evaluate.evaluate_run(run_dir["out"], out=tmp_path / "ev.json")
    ref = json.loads((run_dir["out"] / "metrics.json").read_text())
    assert abs(ev["overall"]["rmse"] - ref["overall"]["rmse"]) <= 1e-9


@pytest.mark.slow
def test_evaluate_new_motion(run_dir, tmp_path, capsys):
    """``--data DIR2`` with one of the run's motions and a new one — a renamed copy of
    the run's other motion, so the frozen basis can represent it: the known motion keeps
    its stored weights (its metrics.json figures); the new one is synthesised (flag
    ``synthesized``: NNLS weights on its torques, then 2 path steps) and reproduced as
    well as in training (measured: rmse 0.0093 → 0.0093, tip 0.87 cm); its program is
    written beside the metrics as the run folder synthesized/, which ``simulate`` plays
    and ``perturb`` pushes (the target found through its config.yaml's data)."""
    from tflearn.io import basis as basis_io
    run = run_dir["out"]
    data2 = tmp_path / "data2"
    data2.mkdir()
    known, other = (p.name for p in run_dir["programs"])
    (data2 / f"{known}.npz").write_bytes((run_dir["data"] / f"{known}.npz").read_bytes())
    (data2 / "unseen.npz").write_bytes((run_dir["data"] / f"{other}.npz").read_bytes())
    out = tmp_path / "eval2.json"
    assert cli.main(["evaluate", str(run), "--data", str(data2), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "unseen" in printed and "(synthesized)" in printed
    ev = json.loads(out.read_text())
    ref = json.loads((run / "metrics.json").read_text())
    assert sorted(ev["motions"]) == sorted([known, "unseen"])
    row_new, row_known = ev["motions"]["unseen"], ev["motions"][known]
    print(f"synthesised copy of {other}: rmse {row_new['rmse']:.4f} (training "
          f"{ref['motions'][other]['rmse']:.4f}), tip {100 * row_new['tip']:.2f} cm (training "
          f"{100 * ref['motions'][other]['tip']:.2f}), torque {row_new['torque_rel_rms']:.4f}")
    assert row_new["synthesized"] is True and row_known["synthesized"] is False
    for key in ("rmse", "tip"):
        assert abs(row_known[key] - ref["motions"][known][key]) <= 1e-6
        assert row_new[key] <= ref["motions"][other][key] + 1e-3
    assert row_new["success"] and ev["complete"] is True
    synth = basis_io.load(tmp_path / "synthesized" / "basis.json")
    assert synth.names == ["unseen"] and synth.basis.M == ev["overall"]["M"]
    assert printed.strip().splitlines()[-1].endswith(f"programs, {tmp_path / 'synthesized'}")
    assert cli.main(["simulate", str(tmp_path / "synthesized"), "--motion", "unseen",
                     "--out", str(tmp_path / "unseen.npz")]) == 0
    assert cli.main(["perturb", str(tmp_path / "synthesized"), "--motion", "unseen", "--controller",
                     "fields", "--no-animation", "--out", str(tmp_path / "push"), "--quiet"]) == 0
    # the path steps trade a little torque fit for path (measured 0.0097 against 0.0062
    # in training), but the frozen basis still explains the torques
    assert row_new["torque_rel_rms"] <= 0.05
    assert ev["overall"]["M"] == ref["overall"]["M"]


# ------------------------------------------------------------ bad input: one line, exit 2

def _train(tmp_path, *overrides, config=None):
    config = config or ROOT / "configs" / "gestures.yaml"
    return cli.train_main([str(config), f"out={tmp_path / 'out'}", "log.progress=false",
                           "log.tensorboard=false", *overrides])


def _one_line_error(capsys, prog: str, *words) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"{prog}: ") and "Traceback" not in err, err
    assert len(err.splitlines()) == 1, err
    for w in words:
        assert str(w) in err, (w, err)
    return err


@pytest.mark.parametrize("content,words", [
    (b"seed: 1  # caf\xe9\n", ["not UTF-8"]),
    (b"solver: {em: [1, 2\n", ["not valid YAML"]),
    (b"- a\n- b\n", ["mapping"]),
    (b"seed: -3\n", ["'seed'", "non-negative"]),
    (b"body: {preset: octopus}\n", ["body", "octopus"]),
    (b"body: {preset: arm, lengths: [0.3, 0.2]}\n", ["body", "3 entries"]),
])
def test_train_bad_config_file(tmp_path, capsys, content, words):
    cfg = tmp_path / "bad.yaml"
    cfg.write_bytes(content)
    assert _train(tmp_path, config=cfg) == 2
    _one_line_error(capsys, "train", *words)
    assert not (tmp_path / "out").exists()


def test_train_data_errors(tmp_path, capsys):
    """A missing folder, an empty one, a folder of bad files, a bad file named alone:
    one line naming it, exit 2, no output folder."""
    empty = tmp_path / "empty"
    empty.mkdir()
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "broken.npz").write_bytes(b"PK\x03\x04 truncated")
    cases = [(tmp_path / "nowhere", "nowhere"), (empty, "no .npz"), (bad, "broken.npz"),
             (bad / "broken.npz", "broken.npz")]
    for data, word in cases:
        assert _train(tmp_path, f"data={data}") == 2
        _one_line_error(capsys, "train", word)
        assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_train_refuses_a_corrupt_checkpoint(run_dir, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(b"\x80\x02 not a checkpoint")
    assert _train(tmp_path, f"data={run_dir['data']}") == 2
    _one_line_error(capsys, "train", out / "checkpoint.pt", "--restart")
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt"]


def test_evaluate_bad_basis_file(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "basis.json").write_text('{"format": "tflearn-basis/9"}')
    assert cli.main(["evaluate", str(run)]) == 2
    _one_line_error(capsys, "tflearn", run / "basis.json")
    assert sorted(p.name for p in run.iterdir()) == ["basis.json"]


def test_a_bug_keeps_its_traceback(tmp_path, monkeypatch, capsys):
    """Only bad input (InputError) becomes one line and exit 2; a genuine error shows its
    traceback, asks to be reported, and exits with 3."""
    from tflearn import train

    def broken(*args, **kw):
        raise ZeroDivisionError("a bug")
    monkeypatch.setattr(train, "run", broken)
    assert _train(tmp_path) == 3
    err = capsys.readouterr().err
    assert "Traceback" in err and "ZeroDivisionError: a bug" in err
    assert "this is a bug in tflearn" in err and "please report it" in err


def test_version_and_help_without_torch():
    """--version and --help answer without importing torch."""
    import subprocess
    import sys
    code = ("import sys; from tflearn import cli\n"
            "for argv in (['--version'], ['--help'], ['simulate', '--help']):\n"
            "    try:\n        cli.main(argv)\n    except SystemExit:\n        pass\n"
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.startswith("tflearn 0.")
    assert "MODEL" in out.stdout and "``" not in out.stdout
    assert out.stdout.strip().splitlines()[-1] == "False"


@pytest.mark.slow
def test_simulate_takes_a_run_folder(run_dir, tmp_path, capsys):
    """Every command that uses a model takes a run folder or its basis.json; a missing
    output folder is created and said so."""
    name = run_dir["programs"][0].name
    out = tmp_path / "new" / "played.npz"
    assert cli.main(["simulate", str(run_dir["out"]), "--motion", name, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"created {out.parent}" in printed and f"wrote {out}" in printed
    assert out.is_file()


def test_bvh_import_and_export(mocap, tmp_path, capsys):
    """``tflearn bvh import`` of two clips and a bad file: the good ones written as
    motions of the body in body.yaml with a report, the bad one skipped with a warning
    naming it; ``tflearn bvh export`` of an imported motion, alone and in the clip's
    skeleton, reads back to the same coordinates (1e-6 rad)."""
    from tflearn import config
    from tflearn.mocap import bvh, retarget
    from tflearn.motions import motion
    from tflearn.physics.body import from_config
    clips = [mocap / "dataset-2_raise-up-right-hand_normal_001.bvh", mocap / "dataset-1_guide_normal_001.bvh"]
    bad = tmp_path / "bad.bvh"
    bad.write_text(clips[0].read_text()[:5000])
    out = tmp_path / "imp"
    with pytest.warns(retarget.BVHWarning, match=f"{bad}: truncated"):
        assert cli.main(["bvh", "import", *map(str, clips), str(bad), "--out", str(out), "--rate", "60"]) == 0
    printed = capsys.readouterr().out
    assert "dataset-1_guide_normal_001: 86 frames at 30 fps" in printed
    assert f"wrote 2 motions, body.yaml and report.json to {out}" in printed
    body = from_config(config.read(out / "body.yaml")["body"])
    rep = json.loads((out / "report.json").read_text())
    assert [c["clip"] for c in rep["clips"]] == [c.stem for c in clips]
    assert body.links[0].offset == pytest.approx(rep["shoulder_zero"])
    m = motion.load(out / f"{clips[0].stem}.npz", body)
    assert m.rate == pytest.approx(60.0) and m.duration == pytest.approx(58 / 30, abs=1 / 60)
    torso = np.load(out / "torso" / f"{clips[0].stem}.npz")
    assert torso["R"].shape == (59, 3, 3) and torso["x"][0, 2] > 1.2      # shoulder height, z up
    for skeleton in (None, clips[0]):
        target = tmp_path / f"{'full' if skeleton else 'arm'}.bvh"
        argv = ["bvh", "export", str(out / f"{clips[0].stem}.npz"), "--body", str(out / "body.yaml"),
                "--out", str(target)] + (["--skeleton", str(skeleton)] if skeleton else [])
        assert cli.main(argv) == 0
        fr = retarget.arm_frames(bvh.read(target), "right")
        q = retarget.coordinates(fr, np.asarray(rep["shoulder_zero"]))[0]
        np.testing.assert_allclose(q, m.q.numpy(), atol=1e-6)
    assert cli.main(["bvh", "import", str(bad), "--out", str(tmp_path / "none"), "--strict"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tflearn: {bad}: truncated") and len(err.strip().splitlines()) == 1
    for folder, extra in (("one", []), ("win", ["--window", "0.5", "1"])):   # the clip alone: its own chart
        assert cli.main(["bvh", "import", str(clips[0]), "--out", str(tmp_path / folder), "--rate", "60",
                         *extra]) == 0
    one, cut = (np.load(tmp_path / f / f"{clips[0].stem}.npz") for f in ("one", "win"))
    assert len(cut["t"]) == 31 and cut["t"][-1] == pytest.approx(0.5, abs=1e-12)
    np.testing.assert_allclose(cut["q"], one["q"][30:61], atol=1e-12, rtol=0)
    win = tmp_path / "win"
    assert cli.main(["bvh", "import", str(clips[0]), "--out", str(win), "--window", "1", "0.5"]) == 2
    assert "with 0 ≤ start < stop (seconds), got (1.0, 0.5)" in capsys.readouterr().err
