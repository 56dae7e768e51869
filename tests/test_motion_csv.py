"""Recordings of joint angles: Euler angles → principal rotation vectors (tflearn.from_euler)
and CSV files (tflearn.read_csv), with errors naming the file, line, column and problem."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

import tflearn
from tflearn.motions import motion as motion_mod
from tflearn.motions.motion import MotionFileError
from tflearn.physics.body import chain

HEADER = "t, shoulder_x, shoulder_y, shoulder_z, elbow, wrist_x, wrist_y, wrist_z"


def _rotvecs(rng, n):
    """n random rotation vectors with ‖v‖ < π − 0.01 (away from the π sign ambiguity)."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return axis * rng.uniform(0, math.pi - 0.01, size=(n, 1))


@pytest.mark.parametrize("order", ["XYZ", "xyz", "ZYX", "zxy", "ZXZ"])
def test_from_euler_round_trip(order):
    rng = np.random.default_rng(3)
    T = 12
    q = np.concatenate([_rotvecs(rng, T), rng.uniform(-2.5, 0.5, (T, 1)), _rotvecs(rng, T)], 1)
    angles = np.concatenate([Rotation.from_rotvec(q[:, :3]).as_euler(order, degrees=True),
                             np.rad2deg(q[:, 3:4]),
                             Rotation.from_rotvec(q[:, 4:]).as_euler(order, degrees=True)], 1)
    # Angles past 180°: ±360° on every Euler angle is the same rotation.
    angles[::2, [0, 2, 4, 6]] += 360.0
    angles[1::3, [1, 5]] -= 720.0
    assert np.abs(angles).max() > 360
    t = np.arange(T) / 100.0
    m = tflearn.from_euler("rec", t, angles, order=order)
    assert m.name == "rec" and m.qd is None
    np.testing.assert_allclose(m.q.numpy(), q, rtol=0, atol=1e-12)
    # Radians too.
    m2 = tflearn.from_euler("rec", t, np.deg2rad(angles), order=order, degrees=False)
    np.testing.assert_allclose(m2.q.numpy(), q, rtol=0, atol=1e-12)


def test_from_euler_conventions():
    """Upper case intrinsic, lower case extrinsic, as scipy: 90° about x then 90° about
    (new / fixed) y; the shoulder's principal vector stays within π; hinges unwrapped."""
    t = np.arange(4) / 10.0
    row = [90, 90, 0, 200, 0, 0, 270]
    intr = tflearn.from_euler("a", t, [row] * 4, order="XYZ")
    extr = tflearn.from_euler("a", t, [row] * 4, order="xyz")
    Rx, Ry = Rotation.from_rotvec([math.pi / 2, 0, 0]), Rotation.from_rotvec([0, math.pi / 2, 0])
    np.testing.assert_allclose(intr.q[0, :3].numpy(), (Rx * Ry).as_rotvec(), atol=1e-12)
    np.testing.assert_allclose(extr.q[0, :3].numpy(), (Ry * Rx).as_rotvec(), atol=1e-12)
    assert intr.q[0, 3] == pytest.approx(math.radians(200))        # a hinge is not wrapped
    np.testing.assert_allclose(intr.q[0, 4:].numpy(), [0, 0, -math.pi / 2], atol=1e-12)
    assert torch.all(intr.q[:, [0, 1, 2, 4, 5, 6]].reshape(-1, 2, 3).norm(dim=-1) <= math.pi + 1e-12)


def test_from_euler_bad_input():
    t = np.arange(5) / 10.0
    with pytest.raises(tflearn.InputError, match=r"motion 'x'.*shape \(5, 6\).*\(T, 7\)"):
        tflearn.from_euler("x", t, np.zeros((5, 6)))
    with pytest.raises(ValueError, match="Euler order"):
        tflearn.from_euler("x", t, np.zeros((5, 7)), order="XXY")
    bad = np.zeros((5, 7))
    bad[2, 4] = np.nan
    with pytest.raises(tflearn.InputError, match="NaN"):
        tflearn.from_euler("x", t, bad)


def _write(path, text):
    path.write_text(text)
    return path


def test_read_csv_round_trip(tmp_path):
    """A CSV of Euler degrees (columns in any order, comments and blank lines) reads back
    the rotation vectors it was written from; it saves and loads as an .npz."""
    rng = np.random.default_rng(7)
    T = 30
    q = np.concatenate([_rotvecs(rng, T), rng.uniform(-2, 0, (T, 1)), _rotvecs(rng, T)], 1)
    t = np.arange(T) / 50.0
    order = "ZYX"
    sh = Rotation.from_rotvec(q[:, :3]).as_euler(order, degrees=True)   # z, y, x angles
    wr = Rotation.from_rotvec(q[:, 4:]).as_euler(order, degrees=True)
    cols = {"t": t, "shoulder_z": sh[:, 0], "shoulder_y": sh[:, 1], "shoulder_x": sh[:, 2],
            "elbow": np.rad2deg(q[:, 3]), "wrist_z": wr[:, 0], "wrist_y": wr[:, 1], "wrist_x": wr[:, 2]}
    names = ["elbow", "t", "wrist_x", "shoulder_x", "shoulder_y", "wrist_z", "shoulder_z", "wrist_y"]
    lines = ["# a recording, degrees", ", ".join(names), ""]
    lines += [",".join(repr(float(cols[n][i])) for n in names) for i in range(T)]
    path = _write(tmp_path / "wave.csv", "\n".join(lines) + "\n")
    m = tflearn.read_csv(path, order=order)
    assert m.name == "wave"
    np.testing.assert_allclose(m.t.numpy(), t, rtol=0, atol=0)
    np.testing.assert_allclose(m.q.numpy(), q, rtol=0, atol=1e-12)
    tflearn.save_motion(m, tmp_path / "wave.npz")
    back = tflearn.load_motion(tmp_path / "wave.npz")
    assert torch.equal(back.q, m.q)


def test_columns():
    assert motion_mod.columns() == [x.strip() for x in HEADER.split(",")]
    assert motion_mod.columns(order="ZYX")[1:4] == ["shoulder_z", "shoulder_y", "shoulder_x"]
    assert motion_mod.columns(chain(2)) == ["t", "link0", "link1"]


def test_read_csv_other_body(tmp_path):
    rows = "".join(f"{i / 10},{10 * i},-5\n" for i in range(5))
    path = _write(tmp_path / "c.csv", "t,link0,link1\n" + rows)
    m = tflearn.read_csv(path, body=chain(2))
    np.testing.assert_allclose(m.q[:, 0].numpy(), np.deg2rad(10 * np.arange(5)))


ROW = "0.{i},1,2,3,-10,4,5,6\n"


@pytest.mark.parametrize("text, match", [
    ("", r"empty"),
    ("# only a comment\n\n", r"empty"),
    ("0,1,2,3,4,5,6,7\n" + "".join(ROW.format(i=i) for i in range(5)),
     r"line 1: missing header row .*t, shoulder_x"),
    ("t,shoulder_x,shoulder_y,shoulder_z,elbow,wrist_x,wrist_y\n",
     r"line 1: header: missing column\(s\) 'wrist_z'"),
    (HEADER + ", extra\n", r"line 1: header: unknown column\(s\) 'extra'"),
    (HEADER + "\n", r"no samples after the header"),
    (HEADER + "\n" + ROW.format(i=0) + "0.1,1,2,3,-10,4,5\n", r"line 3: 7 values, expected 8"),
    (HEADER + "\n" + ROW.format(i=0) + "0.1,1,2,abc,-10,4,5,6\n",
     r"line 3, column 4 \('shoulder_z'\): 'abc' is not a number"),
    (HEADER + "\n" + ROW.format(i=0) + "0.1,1,2,3,nan,4,5,6\n",
     r"line 3, column 5 \('elbow'\): 'nan' is not finite"),
    (HEADER + "\n" + ROW.format(i=0) + "0.1,1,2,3,,4,5,6\n",
     r"line 3, column 5 \('elbow'\): '' is not a number"),
    (HEADER + "\n" + "".join(ROW.format(i=i) for i in (0, 1, 1, 2)),
     r"line 4: times 't' are not strictly increasing"),
    (HEADER + "\n" + "".join(ROW.format(i=i) for i in range(3)), r"3 samples, at least 4"),
])
def test_read_csv_bad_files(tmp_path, text, match):
    path = _write(tmp_path / "bad.csv", text)
    with pytest.raises(MotionFileError, match=match) as err:
        tflearn.read_csv(path)
    assert str(err.value).startswith(str(path))
    assert isinstance(err.value, tflearn.InputError)


def test_read_csv_missing_file_and_bad_order(tmp_path):
    with pytest.raises(MotionFileError, match="no such file"):
        tflearn.read_csv(tmp_path / "nope.csv")
    with pytest.raises(MotionFileError, match="not a regular file"):
        tflearn.read_csv(tmp_path)
    path = _write(tmp_path / "ok.csv", HEADER + "\n" + "".join(ROW.format(i=i) for i in range(5)))
    with pytest.raises(ValueError, match="three different axes"):
        tflearn.read_csv(path, order="ZXZ")
