"""The BVH reader and writer: raw channels against rotations rebuilt by hand, bvhio
parity on the shared clips, bad files, and a write → read round trip."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from tflearn.errors import InputError
from tflearn.mocap import bvh


def _elementary(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return {"X": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
            "Y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "Z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def _raw(path, frame: int):
    """(joint names, channel lists, frame numbers) read with plain string splitting."""
    lines = path.read_text().splitlines()
    names, chans = [], []
    for line in lines:
        tok = line.split()
        if tok[:1] in (["ROOT"], ["JOINT"]):
            names.append(tok[1])
        elif tok[:1] == ["CHANNELS"]:
            chans.append(tok[2:])
        elif tok[:1] == ["MOTION"]:
            break
    start = lines.index("MOTION") + 3
    return names, chans, [float(x) for x in lines[start + frame].split()]


@pytest.mark.parametrize("clip", ["cmu_141_16_wave-hello", "dataset-2_wave-right-hand_normal_001"])
def test_local_rotations_rebuilt_from_raw_channels(mocap, clip):
    """Frame 40's local rotations equal the product of elementary rotations in each
    joint's listed channel order (CMU Z·Y·X, Bandai Z·X·Y), and the translations the
    position channels (else the OFFSET) times the unit."""
    path = mocap / f"{clip}.bvh"
    skel = bvh.read(path)
    names, chans, nums = _raw(path, 40)
    assert list(skel.joints) == names
    col = 0
    orders = set()
    for j, cs in enumerate(chans):
        R = np.eye(3)
        p = skel.offsets[j].copy()
        order = ""
        for c in cs:
            if c.endswith("rotation"):
                R = R @ _elementary(c[0], nums[col])
                order += c[0]
            else:
                p["XYZ".index(c[0])] = nums[col] * skel.scale
            col += 1
        orders.add(order)
        np.testing.assert_allclose(skel.rotations[40, j], R, atol=1e-12)
        np.testing.assert_allclose(skel.positions[40, j], p, atol=1e-12)
    assert col == len(nums) == skel.values.shape[1]
    assert orders == ({"ZYX"} if clip.startswith("cmu") else {"ZXY"})
    assert skel.scale == (bvh.CMU_UNIT if clip.startswith("cmu") else bvh.CM)


def test_units_and_heights(mocap):
    """Hips about 0.96 m (CMU, 17 units) and 0.94 m (Bandai, 94 cm) above the floor."""
    cmu = bvh.read(mocap / "cmu_141_16_wave-hello.bvh")
    ban = bvh.read(mocap / "dataset-1_bye_normal_001.bvh")
    assert cmu.world()[1][0, 0, 1] == pytest.approx(17.0 * bvh.CMU_UNIT, rel=0.1)
    assert ban.world()[1][0, ban.index("Hips"), 1] == pytest.approx(0.94, abs=0.03)


@pytest.mark.parametrize("unit", ["m", "mm", "inch", "CMU's"])
def test_a_files_unit_is_read_from_its_arm(mocap, tmp_path, unit):
    """A Bandai clip written in metres, millimetres, inches or CMU's unit (its offsets and
    position channels) reads back in that unit, by its arm's length (0.47 m): the same
    skeleton in metres, to the writer's 10 digits."""
    skel = bvh.read(mocap / "dataset-1_bye_normal_001.bvh")
    metres = bvh.UNITS[unit]
    values, col = skel.values.copy(), 0
    for channels in skel.channels:
        for c in channels:
            if c.endswith("position"):
                values[:, col] *= skel.scale / metres
            col += 1
    bvh.write(dataclasses.replace(skel, scale=metres), tmp_path / "clip.bvh", values)
    back = bvh.read(tmp_path / "clip.bvh")
    assert back.scale == metres
    np.testing.assert_allclose(back.offsets, skel.offsets, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(back.positions, skel.positions, rtol=1e-9, atol=1e-9)


def test_bvhio_parity(mocap):
    """bvhio 1.5.4 (float32 quaternions) agrees with the reader on two clips to 1e-6."""
    bvhio = pytest.importorskip("bvhio")
    from scipy.spatial.transform import Rotation
    for clip in ("cmu_141_16_wave-hello", "dataset-1_call_normal_001"):
        skel = bvh.read(mocap / f"{clip}.bvh")
        joints = [j for j, _, _ in bvhio.readAsBvh(str(mocap / f"{clip}.bvh")).Root.layout()]
        assert [j.Name for j in joints] == list(skel.joints)
        for k, j in enumerate(joints):
            q = np.array([[f.Rotation.x, f.Rotation.y, f.Rotation.z, f.Rotation.w] for f in j.Keyframes])
            np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), skel.rotations[:, k], atol=1e-6)


SMALL = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Arm
  {
    OFFSET 0 -10 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    End Site
    {
      OFFSET 0 -5 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.5
1 2 3 10 20 30 40 50 60
4 5 6 -10 -20 -30 -40 -50 -60
"""


def _write(tmp_path, text, name="clip.bvh"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_small_file_and_round_trip(tmp_path):
    """A hand-made file reads as written (cm → m) and write → read gives the same numbers."""
    skel = bvh.read(_write(tmp_path, SMALL))
    assert skel.joints == ("Hips", "Arm") and skel.parents == (-1, 0)
    np.testing.assert_allclose(skel.offsets[1], [0, -0.1, 0])
    np.testing.assert_allclose(skel.end_sites[1], [0, -0.05, 0])
    np.testing.assert_allclose(skel.positions[1, 0], [0.04, 0.05, 0.06])
    assert skel.frame_time == 0.5 and skel.frames == 2
    bvh.write(skel, tmp_path / "out.bvh",
              values=bvh.channel_values(skel, skel.rotations, skel.positions))
    again = bvh.read(tmp_path / "out.bvh")
    np.testing.assert_allclose(again.values, skel.values, atol=1e-7)
    np.testing.assert_allclose(again.rotations, skel.rotations, atol=1e-12)


BAD = {
    "truncated at a line end": (SMALL.rsplit("4 5 6", 1)[0],
                                "truncated: 'Frames: 2' but only 1 frame lines"),
    "truncated in the hierarchy": (SMALL[:120], "ends inside the HIERARCHY"),
    "wrong channel count": (SMALL.replace("4 5 6 -10", "4 5 -10"),
                            "line 20: frame 1 has 8 values, the HIERARCHY declares 9 channels"),
    "non-numeric value": (SMALL.replace("40 50 60", "40 abc 60"),
                          "line 19: value 8 (joint 'Arm' Yrotation) 'abc' is not a number"),
    "not finite": (SMALL.replace("40 50 60", "40 nan 60"), "'nan' is not finite"),
    "CHANNELS mismatch": (SMALL.replace("CHANNELS 3 Zrotation", "CHANNELS 4 Zrotation"),
                          "line 10: joint 'Arm': 'End' is not a channel (CHANNELS says 4"),
    "bad OFFSET": (SMALL.replace("OFFSET 0 -10 0", "OFFSET 0 x 0"),
                   "line 8: joint 'Arm' OFFSET: 'x' is not a number"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_files(tmp_path, case):
    text, message = BAD[case]
    path = _write(tmp_path, text)
    with pytest.raises(bvh.BVHError) as err:
        bvh.read(path)
    assert isinstance(err.value, InputError)
    assert str(err.value).startswith(f"{path}: ")
    assert message in str(err.value)
