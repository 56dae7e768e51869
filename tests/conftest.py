"""Shared helpers for the tflearn tests.

Everything is float64 and passed explicitly (``dtype=DT``); the global default dtype is
left alone. Pinocchio (PyPI ``pin``) is the reference implementation for the dynamics
tests and is imported lazily so that the tests that do not need it run without it.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from tflearn.physics import body as tb

DT = torch.float64


@pytest.fixture(autouse=True, scope="session")
def _single_thread():
    """Run torch on one thread for the session.

    The tensors here are tiny (a few 7-vectors); intra-op threading only adds overhead
    (one ODE right-hand side costs ~8 ms on 2 threads against ~1.5 ms on one), and the
    simulation tests make thousands of such calls.
    """
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def rng():
    """A seeded numpy generator (fresh per test, so tests do not depend on order)."""
    return np.random.default_rng(20240611)


@pytest.fixture
def gen():
    """A seeded torch generator (fresh per test)."""
    return torch.Generator().manual_seed(20240611)


# ----------------------------------------------------------------------------- bodies

ARM_OFFSETS = [[0.1, 0.2, -0.3], [0.3, -0.1, 0.2], [-0.2, 0.4, 0.1]]
GRAVITY = (0.0, 0.0, -9.81)


def random_spd3(rng, scale=0.05):
    """A random symmetric positive-definite 3x3 inertia (well conditioned)."""
    A = rng.normal(size=(3, 3))
    return scale * (A @ A.T + 0.5 * np.eye(3))


def unit(rng, n=3):
    x = rng.normal(size=n)
    return x / np.linalg.norm(x)


def make_tree(gravity=(0.0, 0.0, 0.0), seed=7) -> tb.Body:
    """A branching tree with general link data: off-axis centres of mass, full inertia
    matrices, unaligned hinge axes, random joint origins and zero orientations.

    parents [-1, 0, 1, 0, 3], joints [ball, hinge, ball, hinge, ball] (nv = 11).
    """
    r = np.random.default_rng(seed)
    parents = [-1, 0, 1, 0, 3]
    joints = ["ball", "hinge", "ball", "hinge", "ball"]
    links = []
    for i, (p, j) in enumerate(zip(parents, joints)):
        links.append(tb.Link(
            name=f"l{i}", parent=p, joint=j,
            origin=tuple(r.normal(scale=0.2, size=3)) if p >= 0 else (0.0, 0.0, 0.0),
            mass=float(r.uniform(0.5, 2.0)),
            com=tuple(r.normal(scale=0.1, size=3)),
            inertia=tuple(map(tuple, random_spd3(r))),
            offset=tuple(r.uniform(-1.0, 1.0, size=3)),
            axis=tuple(unit(r))))
    return tb.Body(links=tuple(links), gravity=tuple(gravity), tip_link=2,
                   tip_point=tuple(r.normal(scale=0.2, size=3)), name="tree")


def make_body(name: str, gravity=(0.0, 0.0, 0.0)) -> tb.Body:
    if name == "arm":
        return tb.arm(gravity=list(gravity))
    if name == "arm_offsets":
        return tb.arm(gravity=list(gravity), offsets=ARM_OFFSETS)
    if name == "chain3_ball":
        return tb.chain(3, "ball", gravity=gravity)
    if name == "chain4_hinge":
        return tb.chain(4, "hinge", gravity=gravity)
    if name == "tree":
        return make_tree(gravity)
    raise KeyError(name)


BODY_NAMES = ["arm", "arm_offsets", "chain3_ball", "chain4_hinge", "tree"]


# ------------------------------------------------------------------------ pinocchio

def to_pin(body: tb.Body, free_flyer: bool = False):
    """The Pinocchio model of a body. Moving link i is Pinocchio joint i + 1 when the body
    has no fixed joints; a fixed link's inertia is appended to the joint that carries it
    (its parent's, placed by the fixed joint), and its children hang from that joint.
    A free joint is a pin.JointModelFreeFlyer (its velocity and torque halves are in the
    other order: :func:`v_to_pin`).
    ``free_flyer``: the body's base is a massless free-flyer joint (joint 1, so moving
    link i is joint i + 2; nq += 7, nv += 6)."""
    import pinocchio as pin

    model = pin.Model()
    root = model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), "base") if free_flyer else 0
    frames = []                      # per link: (Pinocchio joint id, link frame in it)
    for link in body.links:
        jid, above = (root, pin.SE3.Identity()) if link.parent < 0 else frames[link.parent]
        place = above * pin.SE3(pin.exp3(np.array(link.offset, dtype=float)),
                                np.array(link.origin, dtype=float))
        if link.joint == "fixed":
            frames.append((jid, place))
        else:
            if link.joint == "hinge":
                jm = pin.JointModelRevoluteUnaligned(np.array(link.axis, dtype=float))
            else:
                jm = pin.JointModelSpherical() if link.joint == "ball" else pin.JointModelFreeFlyer()
            frames.append((model.addJoint(jid, jm, place, link.name), pin.SE3.Identity()))
        jid, place = frames[-1]
        model.appendBodyToJoint(
            jid, pin.Inertia(link.mass, np.array(link.com, dtype=float),
                             np.array(link.inertia, dtype=float)), place)
    moving = [f[0] for f, l in zip(frames, body.links) if l.joint != "fixed"]
    assert moving == list(range(root + 1, root + len(moving) + 1))
    model.gravity.linear = np.array(body.gravity, dtype=float)
    return model


def q_to_pin(body: tb.Body, q) -> np.ndarray:
    """tflearn coordinates ν (nv,) → Pinocchio configuration (quaternions XYZW for balls;
    (translation, quaternion) for a free joint)."""
    import pinocchio as pin

    q = np.asarray(q, dtype=float)
    parts = []
    for i, link in enumerate(body.links):
        s = q[body.slice(i)]
        if link.joint == "ball":
            parts.append(pin.Quaternion(pin.exp3(s)).coeffs())
        elif link.joint == "free":
            parts += [s[3:], pin.Quaternion(pin.exp3(s[:3])).coeffs()]
        elif link.joint == "hinge":
            parts.append(s)
    return np.concatenate(parts)


def v_to_pin(body: tb.Body) -> np.ndarray:
    """Index array P with x_pin = x[..., P] for velocities, accelerations and torques: a
    free joint's (angular, linear) halves become Pinocchio's (linear, angular)."""
    idx = np.arange(body.nv)
    for i, link in enumerate(body.links):
        if link.joint == "free":
            s = body.slice(i)
            idx[s] = np.concatenate([idx[s][3:], idx[s][:3]])
    return idx


def full_symmetric(upper: np.ndarray) -> np.ndarray:
    """pin.crba fills only the upper triangle; mirror it."""
    return np.triu(upper) + np.triu(upper, 1).T


# --------------------------------------------------------------------------- states

# Ball-joint rotation angles for the first states: π, just below π, tiny, zero; then π
# again about a signed coordinate axis, so that |v| is π to the last bit.
SPECIAL_ANGLES = [math.pi, math.pi - 1e-9, 1e-9, 0.0, math.pi]


def random_coords(body: tb.Body, rng, n: int) -> np.ndarray:
    """n coordinate vectors (n×nv). Ball angles: the special ones first (each ball joint
    of state k < 5 gets SPECIAL_ANGLES[k]), then uniform in (0, π]; random axes (state 4:
    random signed coordinate axes). Hinge angles uniform in [−2π, 2π]."""
    q = np.zeros((n, body.nv))
    for k in range(n):
        for i, link in enumerate(body.links):
            s = body.slice(i)
            if link.joint == "ball":
                ang = SPECIAL_ANGLES[k] if k < len(SPECIAL_ANGLES) else math.pi - rng.uniform(0.0, math.pi)
                axis = unit(rng)
                if k == 4:
                    axis = np.sign(rng.normal()) * np.eye(3)[rng.integers(3)]
                q[k, s] = ang * axis
            elif link.joint == "hinge":
                q[k, s] = rng.uniform(-2 * math.pi, 2 * math.pi)
    return q


def max_rel_err(x, ref) -> float:
    """max |x − ref| / max(1, max |ref|)."""
    x, ref = np.asarray(x), np.asarray(ref)
    return float(np.abs(x - ref).max() / max(1.0, np.abs(ref).max()))


def wrap_angle(theta):
    """Wrap to (−π, π]."""
    return math.pi - np.mod(math.pi - np.asarray(theta), 2 * math.pi)


# ----------------------------------------------------------------------------- mocap data

def mocap_folder():
    """The shared motion-capture clips: $TFLEARN_MOCAP, else ../shared/data/mocap beside
    the repository (never copied into it)."""
    import os
    from pathlib import Path
    env = os.environ.get("TFLEARN_MOCAP")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"


@pytest.fixture(scope="session")
def mocap():
    """The mocap folder; skips the test when it is absent."""
    path = mocap_folder()
    if not any(path.glob("*.bvh")):
        pytest.skip(f"motion-capture clips not found in {path} (set TFLEARN_MOCAP to their folder)")
    return path


def free_tree(where: int, gravity=(0.0, 0.0, 0.0)) -> tb.Body:
    """conftest's branching tree with link ``where``'s joint made free (root: a floating
    base; 3: a free joint below a moving parent, with its origin and zero orientation)."""
    body = make_tree(gravity)
    links = list(body.links)
    links[where] = replace(links[where], joint="free")
    return body.with_(links=tuple(links))


def random_states(body, rng, n):
    """n random coordinates (n×nv): rotation vectors of uniform angle in [0, π), normal
    hinge angles and translations."""
    q = rng.normal(size=(n, body.nv))
    for i, link in enumerate(body.links):
        s = body.slice(i)
        if link.joint in ("ball", "free"):
            ax = rng.normal(size=(n, 3))
            ax /= np.linalg.norm(ax, axis=1, keepdims=True)
            q[:, s.start:s.start + 3] = ax * rng.uniform(0.0, np.pi, size=(n, 1))
    return q


# ----------------------------------------------------------------------------- a run

@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A run folder without training, for the render, perturb and evaluate tests: two
    short random programs (0.3–0.4 s at 100 Hz) saved as the data, their generating
    fields and weights as basis.json, and a config.yaml pointing at the data."""
    from tflearn import config
    from tflearn.data import gestures
    from tflearn.io import basis as bio
    from tflearn.motions import motion as motion_mod
    base = tmp_path_factory.mktemp("tiny_run")
    data, run = base / "data", base / "run"
    data.mkdir()
    run.mkdir()
    programs = gestures.random_gestures(2, seed=3, ranges={"duration": (0.3, 0.4)})
    for m, _ in gestures.generate(gestures=programs):
        motion_mod.save(m, data / f"{m.name}.npz")
    basis, weights, _ = gestures.library_model(programs)
    z = torch.zeros(2, 7, dtype=DT)
    bio.save(bio.LearnedBasis(tb.arm(), basis, weights, z, z, torch.full((2,), 100.0, dtype=DT)),
             run / "basis.json")
    config.dump(config.load(None, [f"data={data}", f"out={run}"]), run / "config.yaml")
    return {"run": run, "programs": programs}
