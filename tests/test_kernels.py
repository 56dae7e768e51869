"""tflearn.physics.kernels: the compiled articulated-body algorithm and RNEA against the torch recursions
of tflearn.physics.dynamics (which tests/test_dynamics.py and tests/test_free_joint.py hold to
Pinocchio), on every test body, with and without gravity, a moving base and free joints;
when each path is taken; and a blown-up state coming out non-finite."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tflearn.physics import dynamics as D
from tflearn.physics.configspace import joint_rotations

from conftest import BODY_NAMES, DT, GRAVITY, free_tree, make_body, random_coords, random_states

BODIES = [(name, g) for name in BODY_NAMES for g in ((0.0, 0.0, 0.0), GRAVITY)]


def _both(body, q, v, tau, **kw):
    """(compiled, torch) accelerations of the same call: the torch path is the one taken
    when an input needs a gradient."""
    with torch.no_grad():
        fast = D.forward_dynamics(body, q, v, tau, **kw)
    slow = D.forward_dynamics(body, q.clone().requires_grad_(), v, tau, **kw).detach()
    return fast, slow


def _both_rnea(body, q, v, a, **kw):
    with torch.no_grad():
        fast = D.rnea(body, q, v, a, **kw)
    return fast, D.rnea(body, q.clone().requires_grad_(), v, a, **kw).detach()


def _close(fast, slow):
    assert fast.shape == slow.shape and fast.dtype == torch.float64
    assert ((fast - slow).abs() / (1 + slow.abs())).max() < 1e-12


@pytest.mark.parametrize("name,g", BODIES)
def test_compiled_equals_the_torch_recursions(name, g, rng):
    body = make_body(name, g)
    q = torch.as_tensor(random_coords(body, rng, 16), dtype=DT)
    v, tau = (torch.as_tensor(3.0 * rng.normal(size=q.shape), dtype=DT) for _ in range(2))
    _close(*_both(body, q, v, tau))
    g16 = torch.as_tensor(rng.normal(size=(16, 3)), dtype=DT)
    _close(*_both(body, q, v, tau, gravity=g16))
    _close(*_both_rnea(body, q, v, tau))
    _close(*_both_rnea(body, q, v, tau, gravity=g16))
    _close(*_both_rnea(body, q, v, tau, gravity=False))


@pytest.mark.parametrize("where", [0, 3])
def test_compiled_free_joints_and_a_moving_base(where, rng):
    body = free_tree(where, GRAVITY)
    q = torch.as_tensor(random_states(body, rng, 12), dtype=DT)
    v, tau = (torch.as_tensor(2.0 * rng.normal(size=q.shape), dtype=DT) for _ in range(2))
    _close(*_both(body, q, v, tau))
    base = tuple(torch.as_tensor(rng.normal(size=(12, 3)), dtype=DT) for _ in range(3))
    _close(*_both(body, q, v, tau, base=base))
    _close(*_both_rnea(body, q, v, tau))
    _close(*_both_rnea(body, q, v, tau, base=base))


def test_batch_shapes_and_broadcasting(rng):
    body = make_body("arm", GRAVITY)
    q = torch.as_tensor(random_coords(body, rng, 6), dtype=DT).reshape(2, 3, -1)
    v = torch.as_tensor(rng.normal(size=body.nv), dtype=DT)           # broadcast
    tau = torch.zeros(2, 3, body.nv, dtype=DT)
    fast, slow = _both(body, q, v, tau)
    assert fast.shape == (2, 3, body.nv)
    _close(fast, slow)
    with torch.no_grad():
        one = D.forward_dynamics(body, q[1, 2], v, tau[1, 2])
    assert one.shape == (body.nv,) and torch.allclose(one, fast[1, 2], rtol=1e-13, atol=1e-13)


def test_which_path_is_taken(monkeypatch, rng):
    """The compiled path without a gradient on float64 CPU tensors, the torch path with
    one, in float32 — and gradients still flow."""
    body = make_body("arm", GRAVITY)
    calls = []
    real = D._compiled_call
    monkeypatch.setattr(D, "_compiled_call", lambda *a: calls.append(a[0]) or real(*a))
    q = torch.as_tensor(random_coords(body, rng, 3), dtype=DT)
    v = torch.as_tensor(rng.normal(size=q.shape), dtype=DT)
    D.forward_dynamics(body, q, v, v)
    assert calls == ["aba"]
    qg = q.clone().requires_grad_()
    D.forward_dynamics(body, qg, v, v).sum().backward()
    assert len(calls) == 1 and qg.grad is not None and qg.grad.abs().sum() > 0
    D.forward_dynamics(body, q.float(), v.float(), v.float())
    assert len(calls) == 1
    D.rnea(body, q, v, v)
    assert calls == ["aba", "rnea"]


def test_a_blown_up_state_gives_non_finite_accelerations(rng):
    body = make_body("arm")
    q = torch.as_tensor(random_coords(body, rng, 3), dtype=DT)
    v = torch.zeros_like(q)
    v[1, 0] = float("nan")
    with torch.no_grad():
        a = D.forward_dynamics(body, q, v, v)
    assert not torch.isfinite(a[1]).all() and torch.isfinite(a[[0, 2]]).all()


def test_a_singular_joint_inertia_gives_non_finite_accelerations(rng):
    """A massless leaf behind a ball joint (D = 0): NaN from the kernel, not an exception."""
    from tflearn.physics import kernels
    body = make_body("arm")
    tables = list(D._kernel_tables(body))
    tables[7] = tables[7].copy()
    tables[7][-1] = 0.0                                  # the last link's spatial inertia
    assert body.links[-1].joint == "ball"
    q = random_coords(body, rng, 2)
    qdd = np.empty_like(q)
    kernels.aba(*tables, np.zeros((0, 0, 3, 3)), q, *D._kernel_root(body, True), q, q, qdd)
    assert np.isnan(qdd).all()


def test_joint_rotations_are_read_as_given(rng):
    """forward_dynamics_rot takes the rotations from the caller (the simulator's
    quaternions): the compiled path reads the same ones."""
    body = make_body("arm")
    q = torch.as_tensor(random_coords(body, rng, 4), dtype=DT)
    rots = joint_rotations(body, q)
    v, tau = (torch.as_tensor(rng.normal(size=q.shape), dtype=DT) for _ in range(2))
    with torch.no_grad():
        fast = D.forward_dynamics_rot(body, rots, q, v, tau)
    slow = D.forward_dynamics_rot(body, rots, q.clone().requires_grad_(), v, tau).detach()
    _close(fast, slow)
    assert np.isfinite(fast.numpy()).all()


def test_compiled_rotations_from_rotation_vectors_equal_torchs(rng):
    """The kernels' exp([v]×) (what forward_dynamics and rnea hand them: rotation vectors)
    against configspace.rotvec_to_rotmat to rounding: at zero, at tiny angles, on both
    sides of the switch to sinc's series (θ = 4ε^⅙), near and at π, beyond. The compiled
    arithmetic is ordered (and, where the CPU has it, fused) otherwise than torch's, whose
    sin and cos are those of its vector kernels: the bound is the maths', not a measured
    figure. Each takes the quaternion (sinc(h)/2 · v, cos h) to a few ulps (≤ 4ε relative:
    the norm, sin, the quotient, the product) and forms entries 1 − 2(y² + z²), 2(xy ± zw)
    whose error is ≤ 4·|q|²·4ε + 3ε ≤ 16ε, so the two differ by ≤ 32ε (measured: up to 6.5ε
    over 10⁵ random vectors here, 7.3ε with the kernels compiled without FMA and torch's
    AVX2 kernels). A series one term short errs by h⁴/120 ≈ 5e-12 at the switch."""
    from tflearn.physics import kernels
    from tflearn.physics.configspace import rotvec_to_rotmat
    switch = 2 * kernels._SINC_SERIES
    angles = np.concatenate([[0.0, 1e-12, 1e-8, 1e-4, 0.999 * switch, switch, 1.001 * switch,
                              0.5, np.pi - 1e-7, np.pi, np.pi + 1e-9, 5.0],
                             rng.uniform(0, 2 * np.pi, 100)])
    axes = rng.normal(size=(angles.size, 3))
    v = axes / np.linalg.norm(axes, axis=1, keepdims=True) * angles[:, None]
    ref = rotvec_to_rotmat(torch.as_tensor(v, dtype=DT)).numpy()
    mine = np.array([kernels._rodrigues(*x) for x in v]).reshape(-1, 3, 3)
    eps = np.finfo(np.float64).eps
    assert np.abs(mine - ref).max() <= 32 * eps
    n = v[9] / np.pi                                      # at π: R = 2 n nᵀ − 1
    assert np.abs(mine[0] - np.eye(3)).max() == 0         # q = (0, 0, 0, 1): no rounding at all
    assert np.abs(mine[9] - (2 * np.outer(n, n) - np.eye(3))).max() <= 16 * eps   # as above, one side


@pytest.mark.parametrize("name", BODY_NAMES + ["free0", "free3"])
def test_compiled_state_reading_equals_torchs(name, rng):
    """configspace.unpack and position_rate, compiled (no gradient) and in torch: the same
    rotations, principal coordinates (special angles included: π, near π, near 0),
    quaternions and rates; the quaternions' sign and norm as stored."""
    from tflearn.physics.configspace import pack, position_rate, unpack
    body = free_tree(int(name[-1]), GRAVITY) if name.startswith("free") else make_body(name)
    q = torch.as_tensor((random_states if name.startswith("free") else random_coords)(body, rng, 12),
                        dtype=DT)
    v = torch.as_tensor(rng.normal(size=q.shape), dtype=DT)
    y = pack(body, q, v).reshape(3, 4, -1)
    y[0, 0] *= -1.7                                      # the other sign, another norm
    with torch.no_grad():
        fast = unpack(body, y)
        fast_rate = position_rate(body, fast[0], fast[2], fast[3])
    yg = y.clone().requires_grad_()
    slow = unpack(body, yg)
    slow_rate = position_rate(body, slow[0], slow[2], slow[3])
    near = lambda a, b: a.shape == b.shape and torch.allclose(a, b.detach(), rtol=0, atol=1e-13)
    assert all(near(a, b) for a, b in zip(fast[1:], slow[1:]))
    assert all((a is None) == (b is None) and (a is None or near(a, b)) for a, b in zip(fast[0], slow[0]))
    assert near(fast_rate, slow_rate) and fast[1].abs().max() > 0.5


def test_compiled_functions_are_cached_under_a_digest_of_their_sources():
    """numba re-compiles a cached function only when its own file changes: the simulator
    (tflearn.simulation.simkernel) inlines kernels.py's functions and flags and calls
    kernels_state.py's, so all three are cached in one folder named by a digest of the three
    files — a change to any compiles them all afresh — and numba's own setting is left as
    it was for other code."""
    import hashlib
    import os

    import numba

    from tflearn.physics import kernels, kernels_state
    from tflearn.simulation import simkernel
    here = os.path.dirname(os.path.dirname(kernels.__file__))
    digest = hashlib.sha256(b"".join(open(os.path.join(here, n), "rb").read()
                                     for n in kernels.CACHE_SOURCES)).hexdigest()[:16]
    assert set(kernels.CACHE_SOURCES) == {"physics/kernels.py", "physics/kernels_state.py",
                                          "simulation/simkernel.py"}
    cached = {os.path.relpath(os.path.join(d, f), here).replace(os.sep, "/")   # every file numba caches
              for d, _, files in os.walk(here) for f in files
              if f.endswith(".py") and "cache=True" in open(os.path.join(d, f), encoding="utf-8").read()}
    assert cached == set(kernels.CACHE_SOURCES)
    folder = kernels.cache_folder()
    assert folder.endswith(f"numba-{digest}")
    compiled = [f for module in (kernels, kernels_state, simkernel) for f in vars(module).values()
                if hasattr(f, "_cache")]
    assert len(compiled) > 20
    assert all(f._cache._cache_path.startswith(folder) for f in compiled)
    assert numba.config.CACHE_DIR == os.environ.get("NUMBA_CACHE_DIR", "")
