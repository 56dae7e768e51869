"""Unit quaternions by constant tables (rotation matrix, rotation vector, rate) against
roma and finite differences, and the simulator's state layout against a per-link
reference, on bodies with every joint type."""
from __future__ import annotations

import math

import pytest
import roma
import torch
from torch.autograd import gradcheck

from tflearn.physics import configspace as cs
from tflearn.physics import dynamics as D

from conftest import DT, free_tree, make_tree, random_states


def quats(gen, n=64):
    q = torch.randn(n, 4, dtype=DT, generator=gen)
    return q / q.norm(dim=-1, keepdim=True)


def test_quat_to_rotmat_equals_roma(gen):
    q = quats(gen)
    assert float((cs.quat_to_rotmat(q) - roma.unitquat_to_rotmat(q)).abs().max()) <= 1e-15


def test_quat_rate_equals_half_the_product(gen):
    q, w = quats(gen), torch.randn(64, 3, dtype=DT, generator=gen)
    ref = 0.5 * roma.quat_product(q, torch.cat([w, torch.zeros_like(w[:, :1])], -1))
    assert float((cs.quat_rate(q, w) - ref).abs().max()) <= 1e-15


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 0.5, 2.0, math.pi - 1e-6])
def test_quat_to_rotvec_is_roma_shortest_arc(gen, angle):
    axis = torch.randn(16, 3, dtype=DT, generator=gen)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    q = roma.rotvec_to_unitquat(angle * axis)
    q = torch.where(torch.arange(16)[:, None] % 2 == 0, q, -q)       # both signs of the cover
    ref = roma.unitquat_to_rotvec(q, shortest_arc=True)
    assert float((cs.quat_to_rotvec(q) - ref).abs().max()) <= 1e-14
    assert float((cs.quat_to_rotvec(q).norm(dim=-1) - angle).abs().max()) <= 1e-14


def test_quat_to_rotvec_gradients_at_and_near_identity(gen):
    for scale in (0.0, 1e-6, 0.3):
        u = scale * torch.randn(3, 3, dtype=DT, generator=gen)
        q = torch.cat([u, torch.ones(3, 1, dtype=DT)], -1)
        q = (q / q.norm(dim=-1, keepdim=True)).requires_grad_()
        assert gradcheck(cs.quat_to_rotvec, (q,))


@pytest.mark.parametrize("where", [None, 0, 3])
def test_unpack_and_position_rate_against_per_link_reference(rng, where):
    """unpack's rotations, coordinates and quaternions and position_rate's q̇ = ½ q ⊗ ω,
    θ̇, ṫ = R u agree with a link-by-link computation (a tree of ball, hinge and fixed
    joints, with a free joint at the root or below a moving link)."""
    body = make_tree() if where is None else free_tree(where)
    q = torch.as_tensor(random_states(body, rng, 5), dtype=DT)
    v = torch.as_tensor(rng.normal(size=q.shape), dtype=DT)
    y, k = cs.pack(body, q, v), 0
    for link in body.links:                          # quaternions off the unit sphere
        if link.joint in ("ball", "free"):
            y[..., k:k + 4] *= 1.5
        k += cs.POSITION_SIZE.get(link.joint, link.dof)
    rots, coords, qs, v2 = cs.unpack(body, y)
    ref_rots = D.joint_rotations(body, coords)
    rate, k, j = cs.position_rate(body, rots, qs, v2), 0, 0
    for i, link in enumerate(body.links):
        s = body.slice(i)
        if link.joint in ("ball", "free"):
            quat = y[..., k:k + 4] / y[..., k:k + 4].norm(dim=-1, keepdim=True)
            assert torch.allclose(qs[..., j, :], quat, atol=1e-15)
            assert torch.allclose(rots[i], ref_rots[i], atol=1e-13)
            w = torch.cat([v2[..., s][..., :3], torch.zeros_like(v2[..., :1])], -1)
            assert torch.allclose(rate[..., k:k + 4], 0.5 * roma.quat_product(quat, w), atol=1e-14)
            if link.joint == "free":
                u = (rots[i] @ v2[..., s][..., 3:, None])[..., 0]
                assert torch.allclose(rate[..., k + 4:k + 7], u, atol=1e-14)
                assert torch.equal(coords[..., s][..., 3:], y[..., k + 4:k + 7])
            j, k = j + 1, k + cs.POSITION_SIZE[link.joint]
        else:
            assert rots[i] is None
            assert torch.equal(coords[..., s], y[..., k:k + link.dof])
            assert torch.equal(rate[..., k:k + link.dof], v2[..., s])
            k += link.dof
    assert k == cs.n_position(body) and torch.equal(v2, y[..., k:])
    assert torch.allclose(cs.difference(body, q, coords), torch.zeros_like(q), atol=1e-12)


@pytest.mark.parametrize("where", [None, 0, 3])
def test_state_tangent_basis_is_orthonormal_and_leaves_out_each_quaternion(rng, where):
    """BᵀB = I, Bᵀq = 0 for every quaternion q of the state, and [B, q's directions]
    spans the whole state space: the tree's three ball joints (and a free joint)."""
    body = make_tree() if where is None else free_tree(where)
    q = torch.tensor(random_states(body, rng, 16))
    y = cs.pack(body, q, torch.randn(16, body.nv, dtype=torch.float64))
    B = cs.state_tangent_basis(body, y)
    nr = sum(link.joint in ("ball", "free") for link in body.links)
    D = y.shape[-1]
    assert B.shape == (16, D, D - nr)
    assert torch.allclose(B.transpose(-1, -2) @ B, torch.eye(D - nr, dtype=torch.float64), atol=1e-14)
    Q = torch.zeros(16, D, nr, dtype=torch.float64)
    for j, rows in enumerate(cs._layout(body, y.device)["quat"].reshape(-1, 4)):
        Q[:, rows, j] = y[:, rows]
    assert (B.transpose(-1, -2) @ Q).abs().max() < 1e-14
    assert torch.linalg.matrix_rank(torch.cat([B, Q], -1)).eq(D).all()
