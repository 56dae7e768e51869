"""Retargeting BVH arms onto the 7-DOF arm: a known pose, the position check on real
clips, mirroring, mapping errors, the shoulder chart and the BVH round trips."""
from __future__ import annotations

import dataclasses
import json
import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tflearn.mocap import bvh
from tflearn.mocap import retarget as rt

POSE = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Chest
  {
    OFFSET 20 0 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Shoulder_R
    {
      OFFSET 12 0 -5
      CHANNELS 3 Zrotation Xrotation Yrotation
      JOINT UpperArm_R
      {
        OFFSET -5 0 0
        CHANNELS 3 Zrotation Xrotation Yrotation
        JOINT LowerArm_R
        {
          OFFSET -25 0 0
          CHANNELS 3 Zrotation Xrotation Yrotation
          JOINT Hand_R
          {
            OFFSET {forearm} 0 0
            CHANNELS 3 Zrotation Xrotation Yrotation
            End Site
            {
              OFFSET -5 0 0
            }
          }
        }
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.1
{frames}
"""


def _pose_file(tmp_path, frames, forearm="-22", name="pose.bvh"):
    path = tmp_path / name
    path.write_text(POSE.replace("{forearm}", forearm).replace(
        "{frames}", "\n".join(" ".join(map(str, f)) for f in frames)))
    return path


def test_known_pose(tmp_path):
    """A Bandai-named arm with the shoulder turned α about the chest's left axis (its
    local Z), the elbow −60° about its hinge (local Y), a moving and turning chest:
    ν_s = log(Rx(α) Rz(−90°)) (the Bandai zero pose is turned 90° about the vertical
    from the neutral pose), θ = −60°, ν_w = 0, whatever the chest does."""
    alpha = -35.0
    frames = [[1, 90, 3, 30, 10, -20, 0, 0, 0, 0, 0, 0, alpha, 0, 0, 0, 0, -60, 0, 0, 0],
              [0, 95, 0, -15, 5, 40, 0, 0, 0, 0, 0, 0, alpha, 0, 0, 0, 0, -60, 0, 0, 0]]
    fr = rt.arm_frames(bvh.read(_pose_file(tmp_path, frames)), "right")
    q, lost, twist = rt.coordinates(fr, np.zeros(3))
    expect = (Rotation.from_rotvec([math.radians(alpha), 0, 0])
              * Rotation.from_rotvec([0, 0, -math.pi / 2])).as_rotvec()
    for f in range(2):
        np.testing.assert_allclose(q[f, :3], expect, atol=1e-12)
        assert q[f, 3] == pytest.approx(math.radians(-60), abs=1e-12)
        np.testing.assert_allclose(q[f, 4:], 0, atol=1e-12)
    np.testing.assert_allclose(lost, 0, atol=1e-12)
    np.testing.assert_allclose(fr.lengths[:2], [0.25, 0.22])
    # the BVH's elbow in the base frame: the upper arm flexed forward (−y) and up by |α|
    a = math.radians(alpha)
    np.testing.assert_allclose(fr.joints[0, 0], [0, 0.25 * math.sin(a), -0.25 * math.cos(a)], atol=1e-12)


@pytest.mark.parametrize("case,forearm,message", [
    ("zero-length bone", "0", "joint 'Hand_R': zero-length bone from 'LowerArm_R'"),
])
def test_mapping_errors(tmp_path, case, forearm, message):
    path = _pose_file(tmp_path, [[0] * 21] * 2, forearm)
    with pytest.raises(bvh.BVHError, match=message):
        rt.arm_frames(bvh.read(path), "right")


def test_missing_joint_and_folder(tmp_path):
    """A file without the arm's joints is refused naming the joint(s); in a folder the
    good files still load (a warning names the bad one), strict stops at it."""
    good = _pose_file(tmp_path, [[0] * 21] * 2, name="a_good.bvh")
    bad = tmp_path / "b_noarm.bvh"
    bad.write_text(good.read_text().replace("LowerArm_R", "Elbow_R"))
    with pytest.raises(bvh.BVHError, match="no built-in arm map fits"):
        rt.arm_frames(bvh.read(bad), "right")
    amap = rt.MAPS["bandai"]["right"]
    with pytest.raises(bvh.BVHError, match="joint 'LowerArm_R' of the arm map is missing"):
        rt.arm_frames(bvh.read(bad), "right", amap)
    (tmp_path / "c_truncated.bvh").write_text(good.read_text()[:300])
    with pytest.warns(rt.BVHWarning) as rec:
        clips = rt.read_clips([tmp_path])
    assert [c.skeleton.name for c in clips] == ["a_good"]
    msgs = sorted(str(w.message) for w in rec)
    assert len(msgs) == 2 and str(bad) in msgs[0] and "c_truncated.bvh: line" in msgs[1]
    with pytest.raises(bvh.BVHError, match="b_noarm.bvh: no built-in arm map"):
        rt.read_clips([tmp_path], strict=True)
    from tflearn.errors import InputError
    from tflearn.mocap import clips as mocap
    with pytest.raises(InputError, match="out: no clips to import"):
        mocap.import_frames([], tmp_path / "out")


CLIPS = ["dataset-1_guide_normal_001", "dataset-2_raise-up-right-hand_normal_001"]


@pytest.fixture(scope="module")
def imported(mocap):
    frames = [rt.arm_frames(bvh.read(mocap / f"{c}.bvh"), "right") for c in CLIPS]
    return rt.retarget_all(frames)


def test_position_check(imported):
    """tflearn's forward kinematics of the imported coordinates puts the elbow and the
    wrist within 1 cm of the BVH's own (measured ≤ 4e-5 m), also after the best rigid
    alignment; the hinge loses < 0.2° of forearm direction; flexion is negative."""
    for r in imported:
        pe = r.report["position_error_m"]
        assert max(pe["elbow_max"], pe["wrist_max"]) < 1e-4
        assert max(pe["aligned_elbow_max"], pe["aligned_wrist_max"]) < 1e-2
        assert r.report["hinge_lost_deg"]["max"] < 0.2
        assert r.motion.q[:, 3].max() < 0 and r.motion.q[:, 3].min() < -1.5      # bent > 86°
        assert r.report["lengths_m"][:2] == pytest.approx([0.2433, 0.2229], abs=2e-4)


def test_shoulder_chart(mocap):
    """The shared zero orientation keeps the overhead wave's shoulder well inside
    ‖v‖ < π (measured 102°); without it (R0 = I) the same clip reaches 146°."""
    frames = [rt.arm_frames(bvh.read(mocap / f"{c}.bvh"), "right") for c in
              ("dataset-2_wave-right-hand_normal_001", "dataset-1_call_normal_001")]
    zero = rt.shoulder_zero(frames)
    with_chart = max(np.linalg.norm(rt.coordinates(f, zero)[0][:, :3], axis=1).max() for f in frames)
    without = max(np.linalg.norm(rt.coordinates(f, np.zeros(3))[0][:, :3], axis=1).max() for f in frames)
    assert with_chart < math.radians(110) and without > math.radians(140)


def test_mirror(mocap):
    """A mirrored left arm: positions reflected in x, rotation vectors (x, −y, −z),
    the hinge angle kept."""
    skel = bvh.read(mocap / "dataset-2_wave-left-hand_normal_001.bvh")
    a, b = rt.arm_frames(skel, "left"), rt.arm_frames(skel, "left", mirror=True)
    np.testing.assert_allclose(b.joints, a.joints * [-1, 1, 1], atol=1e-12)
    qa, qb = rt.coordinates(a, np.zeros(3))[0], rt.coordinates(b, np.zeros(3))[0]
    np.testing.assert_allclose(qb, qa * [1, -1, -1, 1, 1, -1, -1], atol=1e-9)


def test_round_trips(imported, tmp_path):
    """import → export → import reproduces the arm coordinates to 1e-6 rad: the arm
    written alone, and the clip's skeleton with its arm replaced."""
    r = imported[1]
    q, t = r.motion.q.numpy(), r.motion.t.numpy()
    zero = np.asarray(r.body.links[0].offset)
    bvh.write(rt.arm_skeleton(r.body, t, q), tmp_path / "arm.bvh")
    bvh.write(rt.replace_arm(r.frames, r.body, t, q), tmp_path / "full.bvh")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        alone = rt.arm_frames(bvh.read(tmp_path / "arm.bvh"), "right")
    full = rt.arm_frames(bvh.read(tmp_path / "full.bvh"), "right")
    assert alone.lengths == pytest.approx(r.frames.lengths, abs=1e-9)
    for fr in (alone, full):
        np.testing.assert_allclose(rt.coordinates(fr, zero)[0], q, atol=1e-6)
    # the rest of the skeleton is as recorded
    assert bvh.read(tmp_path / "full.bvh").values[:, :30] == pytest.approx(r.frames.skeleton.values[:, :30])


def test_mocap_config_imports_the_clips(mocap, tmp_path):
    """configs/mocap.yaml names the clips themselves: the run imports all 14 in one chart,
    each on the arm that moves (the three left ones mirrored), the CMU clip at its true
    60 fps, each clip's busiest 0.8 s at 50 Hz (41 samples), with the performer's arm
    as its body."""
    from tflearn import config
    from tflearn.mocap import clips as mocap_mod
    from tflearn.physics.body import from_config
    cfg = config.load(Path(__file__).resolve().parents[1] / "configs" / "mocap.yaml",
                      [f"data={mocap}", f"out={tmp_path}"])
    cfg, report = mocap_mod.import_config(cfg)
    body = from_config(cfg.body)
    assert [link.length for link in body.links] == pytest.approx([0.247045, 0.220879, 0.152216])
    assert cfg.success.rmse == 0.05 and cfg.success.tip == 0.03
    mirrored = sorted(c["clip"] for c in report["clips"] if c["mirrored"])
    assert mirrored == ["dataset-1_punch_normal_001", "dataset-1_respond_normal_001",
                        "dataset-2_wave-left-hand_normal_001"]
    sides = {c["side"] for c in report["clips"] if not c["mirrored"]}
    assert len(report["clips"]) == 14 and sides == {"right"}
    fps = {c["clip"]: c["fps"] for c in report["clips"]}
    assert fps.pop("cmu_141_16_wave-hello") == pytest.approx(60)
    assert list(fps.values()) == pytest.approx([30] * 13, rel=1e-5)         # 1/0.0333333
    for c in report["clips"]:
        assert c["window_s"][1] - c["window_s"][0] == pytest.approx(0.8)
        assert np.load(Path(cfg.data) / c["file"])["q"].shape == (41, 7)


def test_moving_arm(mocap):
    """``moving``: the arm whose hand travels further relative to the chest — the left on
    the left-hand wave and the boxer's first punch, the right on the right-hand wave;
    on the two-handed wave (5.3 m against 5.1 m) the preferred right."""
    names = {"dataset-2_wave-left-hand_normal_001": "left", "dataset-1_punch_normal_001": "left",
             "dataset-2_wave-right-hand_normal_001": "right", "dataset-2_wave-both-hands_normal_001": "right"}
    for name, side in names.items():
        assert rt.moving_arm(bvh.read(mocap / f"{name}.bvh")) == side, name
    both = bvh.read(mocap / "dataset-2_wave-both-hands_normal_001.bvh")
    assert rt.hand_travel(rt.arm_frames(both, "left")) > rt.hand_travel(rt.arm_frames(both, "right"))
    assert rt.moving_arm(both, prefer="left") == "left"


def test_busiest_window():
    """The busiest window has the largest joint path length of all windows of its length
    (brute force), on a motion whose burst is at a known time."""
    from tflearn.mocap.clips import busiest_window
    from tflearn.motions.motion import Motion
    from tflearn.physics.body import arm
    t = np.arange(301) / 100.0
    q = np.zeros((301, 7))
    q[:, 3] = -1.0 + 0.8 * np.exp(-((t - 2.1) / 0.15) ** 2) + 0.05 * np.sin(7 * t)
    m = Motion("burst", t, q, None, arm())
    start, stop = busiest_window(m, 0.5)
    assert stop - start == pytest.approx(0.5) and start < 2.1 < stop
    step = np.abs(np.diff(q[:, 3]))
    lengths = [step[i:i + 50].sum() for i in range(251)]
    assert step[round(start * 100):round(stop * 100)].sum() == pytest.approx(max(lengths), rel=1e-12)


def test_per_clip_choices_and_one_chart(mocap, tmp_path):
    """Per-clip choices (``--arm moving``, ``--arm CLIP=SIDE``, ``--fps CLIP=F``) bring
    every clip onto one model arm; an import into a folder holding other clips in another
    chart is refused, ``--like`` adds them in its chart (the earlier clips' files
    untouched), and a clip imported again replaces its files (pieces of a whole clip
    removed); a folder of motions in another body is refused by ``import_like``."""
    from tflearn import cli, config
    from tflearn.errors import InputError
    from tflearn.mocap import clips as mocap_mod
    left, right = (mocap / f"dataset-2_wave-{s}-hand_normal_001.bvh" for s in ("left", "right"))
    out = tmp_path / "one"
    assert cli.main(["bvh", "import", str(left), str(right), "--arm", "moving", "--fps",
                     f"{right.stem}=60", "--rate", "50", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    got = {c["clip"]: (c["side"], c["mirrored"], round(c["fps"], 3)) for c in report["clips"]}
    assert got == {left.stem: ("left", True, 30.0), right.stem: ("right", False, 60.0)}
    opts = mocap_mod.ImportOptions(side="left", clips={right.stem: {"arm": "right"}})
    assert opts.model_side == "right" and mocap_mod.ImportOptions(side="left").model_side == "left"
    assert mocap_mod.ImportOptions(side="left", mirror=True).model_side == "right"
    with pytest.raises(InputError, match="its choices are arm"):
        mocap_mod.ImportOptions(clips={"x": {"arm": "up"}})

    guide, call = (mocap / f"dataset-1_{n}_normal_001.bvh" for n in ("guide", "call"))
    out = tmp_path / "run"
    mocap_mod.import_clips([guide], out, mocap_mod.ImportOptions(rate=50))
    before = (out / f"{guide.stem}.npz").read_bytes(), (out / "body.yaml").read_text()
    refused = f"holds an import of other clips \\({guide.stem}\\) in another body"
    with pytest.raises(InputError, match=refused):
        mocap_mod.import_clips([call], out, mocap_mod.ImportOptions(rate=50))
    like = mocap_mod.like_body(out)
    mocap_mod.import_clips([call], out, mocap_mod.ImportOptions(rate=50, like=like))
    report = json.loads((out / "report.json").read_text())
    assert [c["clip"] for c in report["clips"]] == [guide.stem, call.stem]
    assert ((out / f"{guide.stem}.npz").read_bytes(), (out / "body.yaml").read_text()) == before
    mocap_mod.import_clips([guide], out, mocap_mod.ImportOptions(rate=50, like=like, split=0.8))
    files = sorted(p.name for p in out.glob("*.npz"))
    assert files == [f"{call.stem}.npz"] + [f"{guide.stem}_part{k:02d}.npz" for k in range(4)]  # 2.8 s
    assert not (out / "torso" / f"{guide.stem}.npz").exists()

    cfg = config.load(None, [f"out={tmp_path}"])                  # a run on the default arm
    with pytest.raises(InputError, match="not in the run's body \\(shoulder chart [0-9.]+° from"):
        mocap_mod.import_like(cfg, str(out), tmp_path / "new")
    assert mocap_mod.import_like(config.load(None, ["body=" + json.dumps(like)]), str(out), tmp_path) is None
    folder = mocap_mod.import_like(cfg.replace(bvh=config.BvhSection(rate=50)), str(right), tmp_path / "new")
    assert mocap_mod.same_body(config.read(folder / "body.yaml")["body"], cfg.body)
    (tmp_path / "planar.yaml").write_text("body: {preset: chain}\n")
    with pytest.raises(InputError, match="planar.yaml: its body: section is not an arm"):
        mocap_mod.like_body(tmp_path / "planar.yaml")


def test_configured_map(tmp_path):
    """A map given as a mapping (a YAML file's) reads a skeleton with other joint
    names like the built-in one; bad maps are refused naming the file."""
    text = _pose_file(tmp_path, [[0, 90, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, -35, 0, 0, 0, 0, -60, 0, 0, 0]] * 2
                      ).read_text()
    for a, b in (("Chest", "Torso"), ("UpperArm_R", "Arm"), ("LowerArm_R", "Elbow"), ("Hand_R", "Wrist")):
        text = text.replace(a, b)
    path = tmp_path / "other.bvh"
    path.write_text(text)
    doc = {"chest": "Torso", "shoulder": "Arm", "elbow": "Elbow", "wrist": "Wrist",
           "up": [1, 0, 0], "left": [0, 0, 1], "hinge": [0, 1, 0]}
    amap = rt.map_from_dict(doc, "map.yaml")
    q = rt.coordinates(rt.arm_frames(bvh.read(path), "right", amap), np.zeros(3))[0]
    assert q[0, 3] == pytest.approx(math.radians(-60), abs=1e-12)
    with pytest.raises(bvh.BVHError, match="map.yaml: arm map: up must be 3 numbers"):
        rt.map_from_dict({**doc, "up": [1, 0]}, "map.yaml")
    with pytest.raises(bvh.BVHError, match="map.yaml: an arm map needs the keys"):
        rt.map_from_dict({**doc, "elbo": "x"}, "map.yaml")


def test_a_skeleton_no_map_knows_is_mapped_from_its_names_and_rest_offsets(mocap, tmp_path):
    """The CMU clip with Mixamo's joint names (``mixamorig:RightHand`` …) fits no
    built-in map; the map read from its names and rest offsets finds the CMU chain, its
    chest axes within 2° of the built-in ones (measured 1.1° and 1.2°: the neck and the
    shoulders do not lie exactly on them), and the clip imports to the same coordinates
    (measured to 2e-15 rad): the shoulder's chart takes a turned base frame back; its
    length unit, CMU's, is read from its arm (bvh.file_unit). On a Bandai skeleton the
    map so read is the built-in one but for its hinge (fitted)."""
    cmu = mocap / "cmu_141_16_wave-hello.bvh"
    renamed = tmp_path / "mixamo.bvh"
    renamed.write_text(re.sub(r"(ROOT|JOINT) (\S+)", r"\1 mixamorig:\2", cmu.read_text()))
    skel, ref = bvh.read(renamed), rt.MAPS["cmu"]["right"]
    amap = rt.find_map(skel, "right")
    assert amap.names == tuple(f"mixamorig:{n}" for n in ref.names) and amap.hinge is None
    for axis in ("up", "left"):
        assert math.degrees(math.acos(np.dot(getattr(amap, axis), getattr(ref, axis)))) < 2.0
    both = [rt.retarget_all([rt.arm_frames(s, "right")])[0] for s in (bvh.read(cmu), skel)]
    assert torch.allclose(both[0].motion.q, both[1].motion.q, rtol=0, atol=1e-9)
    assert skel.scale == bvh.CMU_UNIT and both[0].frames.lengths == both[1].frames.lengths   # by its arm
    bandai = bvh.read(mocap / "dataset-1_bye_normal_001.bvh")
    for side in ("right", "left"):
        assert rt.infer_map(bandai, side) == dataclasses.replace(rt.MAPS["bandai"][side], hinge=None)

def test_train_data_names_bvh(mocap, tmp_path):
    """``data:`` naming a BVH clip: the run imports it into OUT/imported with the bvh
    section's options, trains on the folder written and takes the performer's body. The
    window [0.5, 1.25] s at 50 Hz is the whole clip's import cut there (38 samples,
    coordinates equal to 1e-12, times from 0, clip times 0.5–1.24 s), and the torso's
    frames cover it; a window longer than every clip, a config mixing clips and motions,
    and a replaced body are reported, by ``train`` before any work."""
    from tflearn import config, train
    from tflearn.errors import InputError
    from tflearn.mocap import clips as mocap_mod
    from tflearn.motions import motion
    from tflearn.physics.body import from_config
    clip = mocap / "dataset-2_wave-right-hand_normal_001.bvh"
    base = [f"data={clip}", f"out={tmp_path / 'run'}", "bvh.rate=50"]
    cfg, imported = mocap_mod.import_config(config.load(None, base + ["bvh.window=[0.5,1.25]"]))
    folder, body = tmp_path / "run" / "imported", from_config(cfg.body)
    assert cfg.data == str(folder) and imported["clips"][0]["window_s"] == pytest.approx([0.5, 1.24])
    whole = mocap_mod.import_clips([clip], tmp_path / "whole", mocap_mod.ImportOptions(rate=50))
    assert cfg.body == whole["body"] == imported["body"]
    got = motion.load(folder / "dataset-2_wave-right-hand_normal_001.npz", body)
    want = motion.load(tmp_path / "whole" / "dataset-2_wave-right-hand_normal_001.npz", body)
    assert got.T == 38 and float(got.t[0]) == 0.0 and abs(float(got.t[-1]) - 0.74) < 1e-12
    assert torch.allclose(got.q, want.q[25:63], atol=1e-12, rtol=0)
    torso = np.load(folder / "torso" / "dataset-2_wave-right-hand_normal_001.npz")
    assert -1 / 30 < torso["t"][0] <= 0.0 and 0.74 <= torso["t"][-1] < 0.74 + 1 / 30
    with pytest.warns(rt.BVHWarning, match="window \\[0.0, 100.0\\] s ends after the clip"):
        with pytest.raises(InputError, match="no clip is as long as the window"):
            train.run(config.load(None, base + ["bvh.window=[0,100]"]))
    with pytest.raises(InputError, match="ends after the clip"):
        train.run(config.load(None, base + ["bvh.window=[0,100]", "strict=true"]))
    with pytest.raises(InputError, match="names BVH clips and motion files together"):
        train.run(config.load(None, [f"data=[{clip}, {folder}/x.npz]", f"out={tmp_path}"]))
    with pytest.warns(UserWarning, match="config's body: section is replaced"):
        mocap_mod.import_config(config.load(None, base + ["body.lengths=[0.3,0.3,0.1]"]))


def test_split_into_pieces(mocap, tmp_path):
    """``split``: the wave (6.2 s at 50 Hz) cut into 0.8 s pieces is 8 motions NAME_part00…07
    (the last 0.58 s), equal to the whole import's samples (1e-12) and sharing each boundary
    sample, each with a torso file covering it and its clip times as ``window_s``; its
    window [0.5, 2.4] s in 0.8 s pieces is 2 (the 0.3 s remainder joins the last, 1.1 s),
    printed as one clip line. 0.75 s, not a whole number of samples at 50 Hz, is rounded
    to 38 sample intervals, the pieces still sharing their boundaries. A split ≤ 0 is
    refused."""
    from tflearn import config
    from tflearn.errors import InputError
    from tflearn.mocap import clips as mocap_mod
    from tflearn.motions import motion
    clip = mocap / "dataset-2_wave-right-hand_normal_001.bvh"
    name = clip.stem
    whole = mocap_mod.import_clips([clip], tmp_path / "whole", mocap_mod.ImportOptions(rate=50))
    body = config.read_body(tmp_path / "whole" / "body.yaml")
    full = motion.load(tmp_path / "whole" / f"{name}.npz", body)
    report = mocap_mod.import_clips([clip], tmp_path / "split", mocap_mod.ImportOptions(rate=50, split=0.8))
    assert [c["file"] for c in report["clips"]] == [f"{name}_part{k:02d}.npz" for k in range(8)]
    assert report["body"] == whole["body"]
    pieces = [motion.load(tmp_path / "split" / c["file"], body) for c in report["clips"]]
    first = 0
    for k, (c, p) in enumerate(zip(report["clips"], pieces)):
        assert torch.allclose(p.q, full.q[first:first + p.T], atol=1e-12, rtol=0), k
        assert float(p.t[0]) == 0.0 and c["window_s"] == pytest.approx([float(full.t[first]),
                                                                        float(full.t[first + p.T - 1])])
        torso = np.load(tmp_path / "split" / "torso" / c["file"])
        assert torso["t"][0] <= 0.0 and torso["t"][-1] >= float(p.t[-1])
        first += p.T - 1                                     # the boundary sample is shared
    assert first == full.T - 1 and [p.T for p in pieces] == [41] * 7 + [30]
    report = mocap_mod.import_clips([clip], tmp_path / "odd", mocap_mod.ImportOptions(rate=50, split=0.75))
    odd = [motion.load(tmp_path / "odd" / c["file"], body) for c in report["clips"]]
    assert [p.T for p in odd] == [39] * 7 + [44]             # 0.75 s is 38 intervals at 50 Hz
    assert all(torch.equal(a.q[-1], b.q[0]) for a, b in zip(odd, odd[1:]))
    report = mocap_mod.import_clips([clip], tmp_path / "window", mocap_mod.ImportOptions(
        rate=50, window=(0.5, 2.4), split=0.8))
    assert sum((c["window_s"] for c in report["clips"]), []) == pytest.approx([0.5, 1.3, 1.3, 2.4])
    lines = mocap_mod.report_lines(report)
    assert len(lines) == 1 and lines[0].endswith("cut into 2 pieces")
    with pytest.raises(InputError, match="a split is a piece's length"):
        mocap_mod.ImportOptions(split=0.0)
    with pytest.raises(config.ConfigError, match="split"):
        config.load(None, ["bvh.split=0"])
