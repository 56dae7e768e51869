"""Body presets, anatomy conventions and tree configs."""
import json
import math

import numpy as np
import pytest
import torch

from tflearn.physics import body as tb
from tflearn.physics import dynamics

DT = torch.float64


def test_arm_defaults_match_the_issue():
    arm = tb.arm()
    assert [l.joint for l in arm.links] == ["ball", "hinge", "ball"]
    assert arm.nv == 7 and arm.blocks == [3, 1, 3]
    assert [l.length for l in arm.links] == [0.30, 0.27, 0.19]
    assert [l.mass for l in arm.links] == [2.0, 1.2, 0.45]
    assert [l.radius for l in arm.links] == [0.04, 0.035, 0.03]
    assert arm.gravity == (0.0, 0.0, 0.0) and arm.damping == 0.0
    upper = arm.links[0]
    # Uniform solid cylinder along -z: Ixx = Iyy = m(3r^2 + L^2)/12, Izz = m r^2 / 2.
    assert upper.com == (0.0, 0.0, -0.15)
    assert np.isclose(upper.inertia[0][0], 2.0 * (3 * 0.04**2 + 0.30**2) / 12)
    assert np.isclose(upper.inertia[2][2], 2.0 * 0.04**2 / 2)


def test_rest_pose_hangs_down():
    arm = tb.arm()
    x = dynamics.forward_kinematics(arm, torch.zeros(7, dtype=DT))
    expected = [[0, 0, 0], [0, 0, -0.30], [0, 0, -0.57], [0, 0, -0.76]]
    assert torch.allclose(x, torch.tensor(expected, dtype=DT), atol=1e-15)


def test_come_here_centre_raises_upper_arm_forward_forearm_up():
    arm = tb.arm()
    q = torch.tensor([-math.pi / 2, 0, 0, -math.pi / 2, 0, 0, 0], dtype=DT)
    x = dynamics.forward_kinematics(arm, q)
    assert torch.allclose(x[1], torch.tensor([0, -0.30, 0], dtype=DT), atol=1e-12)   # elbow forward (-y)
    assert torch.allclose(x[2], torch.tensor([0, -0.30, 0.27], dtype=DT), atol=1e-12)  # forearm up (+z)


def test_negative_shoulder_y_abducts_to_the_left_side():
    arm = tb.arm()
    q = torch.tensor([0, -math.pi / 2, 0, 0, 0, 0, 0], dtype=DT)
    elbow = dynamics.forward_kinematics(arm, q)[1]
    assert torch.allclose(elbow, torch.tensor([0.30, 0, 0], dtype=DT), atol=1e-12)


def test_zero_orientation_offset_composes_on_the_parent_side():
    off = [0.0, 0.0, 0.0]
    arm = tb.arm(offsets=[[math.pi / 2, 0, 0], off, off])
    plain = tb.arm()
    # R = R0 exp(v): with R0 = Rx(pi/2) the rest pose equals the plain arm at v = (pi/2, 0, 0).
    q = torch.zeros(7, dtype=DT)
    q_plain = torch.tensor([math.pi / 2, 0, 0, 0, 0, 0, 0], dtype=DT)
    assert torch.allclose(dynamics.forward_kinematics(arm, q),
                          dynamics.forward_kinematics(plain, q_plain), atol=1e-12)


def test_tree_config_equals_the_preset():
    cfg = {"links": [
        {"name": "upper_arm", "parent": -1, "joint": "ball", "origin": [0, 0, 0],
         "length": 0.30, "mass": 2.0, "radius": 0.04},
        {"name": "forearm", "parent": 0, "joint": "hinge", "origin": [0, 0, -0.30],
         "length": 0.27, "mass": 1.2, "radius": 0.035, "axis": [1, 0, 0]},
        {"name": "hand", "parent": 1, "joint": "ball", "origin": [0, 0, -0.27],
         "length": 0.19, "mass": 0.45, "radius": 0.03}],
        "tip": {"link": 2, "point": [0, 0, -0.19]}}
    tree = tb.from_config(cfg)
    arm = tb.from_config({"preset": "arm"})
    g = torch.Generator().manual_seed(0)
    q, v, a = (torch.randn(4, 7, generator=g, dtype=DT) for _ in range(3))
    assert torch.allclose(dynamics.rnea(tree, q, v, a), dynamics.rnea(arm, q, v, a), atol=1e-13)
    assert torch.allclose(dynamics.forward_kinematics(tree, q), dynamics.forward_kinematics(arm, q))


def test_general_links_in_a_config():
    """Links given by mass, centre of mass and inertia (no cylinder size)."""
    inertia = [[0.02, 0.001, 0.0], [0.001, 0.03, 0.0], [0.0, 0.0, 0.01]]
    body = tb.from_config({"links": [
        {"name": "base", "parent": -1, "joint": "ball", "origin": [0, 0, 0], "mass": 2.0,
         "com": [0.0, 0.01, -0.1], "inertia": inertia},
        {"parent": 0, "joint": "hinge", "origin": [0, 0, -0.2], "length": 0.2, "mass": 1.0,
         "radius": 0.03}]})
    assert body.links[0].inertia == tuple(map(tuple, inertia))
    assert body.links[0].com == (0.0, 0.01, -0.1) and body.links[1].name == "link1"
    assert body.tip_point == (0, 0, -0.2) and body.nv == 4
    with pytest.raises(ValueError, match=r"body\.links\[0\]: .*'mass'"):
        tb.from_config({"links": [{"parent": -1, "joint": "ball", "origin": [0, 0, 0],
                                   "inertia": inertia}]})


@pytest.mark.parametrize("body", [tb.arm(offsets=[[0.1, 0, 0], [0, 0, 0], [0, 0.2, 0]]),
                                  tb.chain(3, "ball"), tb.chain(2, "hinge", damping=0.3)])
def test_json_form_round_trips(body):
    doc = json.loads(json.dumps(body.to_dict()))
    assert tb.from_dict(doc) == body and tb.from_dict(doc).to_dict() == doc


def test_preset_overrides():
    b = tb.from_config({"preset": "arm", "gravity": [0, 0, -9.81], "masses": [1, 1, 1]})
    assert b.gravity == (0.0, 0.0, -9.81) and [l.mass for l in b.links] == [1, 1, 1]
    chain = tb.from_config({"preset": "chain", "n": 4, "joint": "hinge"})
    assert chain.nv == 4


@pytest.mark.parametrize("cfg, words", [
    ({"preset": "octopus"}, "unknown preset"),
    ({"preset": "arm", "lengths": [0.3, 0.2]}, "lengths needs 3"),
    ({"preset": "arm", "wings": 2}, "wings"),
    ({"links": [{"parent": 0, "joint": "ball", "origin": [0, 0, 0], "length": 1, "mass": 1,
                 "radius": 0.1}]}, "parent index"),
    ({"links": [{"parent": -1, "joint": "slider", "origin": [0, 0, 0], "length": 1, "mass": 1,
                 "radius": 0.1}]}, "unknown joint type"),
    ({"links": [{"parent": -1, "joint": "ball", "origin": [0, 0, 0], "length": 1, "mass": -1,
                 "radius": 0.1}]}, "mass must be positive"),
    ({"links": [{"parent": -1, "joint": "ball", "origin": [0, 0, 0], "mass": 1,
                 "radius": 0.1}]}, r"body\.links\[0\]: missing key 'length'"),
])
def test_bad_body_configs_are_refused_with_a_reason(cfg, words):
    with pytest.raises(ValueError, match=words):
        tb.from_config(cfg)
