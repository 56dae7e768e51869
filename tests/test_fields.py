"""tflearn.model (fields, weights, program): time profiles, stiffness parametrisations, field
basis, weights, programs."""
from __future__ import annotations

import math

import pytest
import torch
from torch.autograd import gradcheck
from torch.func import functional_call

from tflearn.model.fields import ETA_MAX, K_KINDS, K_RANGE, FieldBasis, Stiffness
from tflearn.model.program import FieldProgram
from tflearn.model.weights import MotionWeights, pulse_profile, pulse_slope, step_profile, step_slope

from conftest import DT


def _t(x):
    return torch.as_tensor(x, dtype=DT)


def psi_ref(u):
    u = min(max(u, 0.0), 1.0)
    return u - math.sin(2 * math.pi * u) / (2 * math.pi)


def phi_ref(u):
    u = min(max(u, 0.0), 1.0)
    return 0.5 * (1 - math.cos(2 * math.pi * u))


# ------------------------------------------------------------------------ profiles

def test_profile_values():
    u = _t([0.0, 0.5, 1.0, -1.0, 2.0, 0.25, 0.75])
    psi = step_profile(u)
    phi = pulse_profile(u)
    expect_psi = _t([0.0, 0.5, 1.0, 0.0, 1.0, 0.25 - 1 / (2 * math.pi), 0.75 + 1 / (2 * math.pi)])
    expect_phi = _t([0.0, 1.0, 0.0, 0.0, 0.0, 0.5, 0.5])
    assert psi.dtype == DT and phi.dtype == DT
    assert float((psi - expect_psi).abs().max()) <= 1e-15
    assert float((phi - expect_phi).abs().max()) <= 1e-15


def test_profiles_are_c1():
    """Derivatives vanish at the joins 0 and 1 (from both sides), and match the closed
    forms ψ' = 1 − cos 2πu, φ' = π sin 2πu inside."""
    u = _t([0.0, 1.0, -1e-6, 1e-6, 1 - 1e-6, 1 + 1e-6, -0.5, 1.5, 0.3, 0.8]).requires_grad_(True)
    (dpsi,) = torch.autograd.grad(step_profile(u).sum(), u)
    (dphi,) = torch.autograd.grad(pulse_profile(u).sum(), u)
    assert float(dpsi[:8].abs().max()) <= 1e-10   # 1 − cos(2π·1e-6) ≈ 2e-11
    assert float(dphi[:8].abs().max()) <= 1e-4    # π sin(2π·1e-6) ≈ 2e-5
    assert float(dphi[:2].abs().max()) <= 1e-15
    inner = u.detach()[8:]
    assert torch.allclose(dpsi[8:], 1 - torch.cos(2 * math.pi * inner), rtol=0, atol=1e-14)
    assert torch.allclose(dphi[8:], math.pi * torch.sin(2 * math.pi * inner), rtol=0, atol=1e-14)
    # step_slope / pulse_slope (EM's closed-form Jacobian) are these derivatives everywhere
    assert torch.allclose(step_slope(u.detach()), dpsi, rtol=0, atol=1e-15)
    assert torch.allclose(pulse_slope(u.detach()), dphi, rtol=0, atol=1e-15)
    # Values are continuous across the joins too.
    eps = _t([-1e-9, 1e-9])
    assert float(step_profile(eps).abs().max()) <= 1e-9
    assert float((step_profile(1 + eps) - 1).abs().max()) <= 1e-9
    assert float(pulse_profile(eps).abs().max()) <= 1e-9


# ---------------------------------------------------------------------- stiffness

def _spd(gen, M, n):
    A = torch.randn(M, n, n, dtype=DT, generator=gen)
    return A @ A.transpose(-1, -2) + 0.5 * torch.eye(n, dtype=DT)


def _block_diag(gen, M, blocks):
    out = []
    for _ in range(M):
        out.append(torch.block_diag(*[_spd(gen, 1, b)[0] for b in blocks]))
    return torch.stack(out)


def _given_K(kind, gen, M=3, n=7):
    if kind == "scalar":
        return torch.diag_embed(_t([0.5, 2.0, 7.5])[:, None].expand(M, n).clone())
    if kind == "diag":
        return torch.diag_embed(0.2 + 3 * torch.rand(M, n, dtype=DT, generator=gen))
    if kind == "block":
        return _block_diag(gen, M, [3, 1, 3])
    return _spd(gen, M, n)


@pytest.mark.parametrize("kind", K_KINDS)
def test_stiffness_reproduces_K_and_stays_pd(kind, gen):
    K = _given_K(kind, gen)
    st = Stiffness(K, kind=kind, blocks=[3, 1, 3] if kind == "block" else None)
    out = st().detach()
    assert out.shape == (3, 7, 7) and out.dtype == DT
    assert float((out - K).abs().max()) <= 1e-12 * float(K.abs().max())
    pattern = (K != 0)
    with torch.no_grad():
        st.raw.add_(0.7 * torch.randn(st.raw.shape, dtype=DT, generator=gen))
    K2 = st().detach()
    assert float((K2 - K).abs().max()) > 1e-2  # the perturbation did change K
    assert torch.equal(K2, K2.transpose(-1, -2))
    assert float(torch.linalg.eigvalsh(K2).min()) > 0.0
    # The sparsity of the kind survives any raw values.
    assert bool((K2[~pattern] == 0).all())


def test_stiffness_block_projects_off_block_entries(gen):
    """A full K given to a block stiffness is read on its block pattern (the blocks'
    Cholesky factors), so the result is the block-diagonal part of K."""
    K = _spd(gen, 2, 7)
    st = Stiffness(K, kind="block", blocks=[3, 1, 3])
    mask = torch.block_diag(torch.ones(3, 3), torch.ones(1, 1), torch.ones(3, 3)).bool()
    expect = torch.where(mask, K, torch.zeros_like(K))
    assert float((st().detach() - expect).abs().max()) <= 1e-12 * float(K.abs().max())


def test_stiffness_rejects_bad_input():
    with pytest.raises(ValueError):
        Stiffness(torch.eye(3, dtype=DT)[None], kind="cholesky")
    with pytest.raises(ValueError):
        Stiffness(torch.eye(3, dtype=DT)[None], kind="block", blocks=[1, 1])


# ---------------------------------------------------------------------- basis

def _basis(gen, M=3, n=7, kind="block"):
    eta = 0.5 * torch.randn(M, n, dtype=DT, generator=gen)
    K = _given_K(kind, gen, M, n)
    return FieldBasis(eta, 0.5 * K, kind=kind, blocks=[3, 1, 3] if kind == "block" else None)


@pytest.mark.parametrize("kind", K_KINDS)
def test_basis_is_gradient_of_gaussian(kind, gen):
    """χ_i = ∇ exp(−½ dᵀK_i d) by autograd, for every kind (scalar and diag take K d
    elementwise, the others as a matrix product)."""
    basis = _basis(gen, kind=kind)
    q = (basis.eta.detach()[1] + 0.5 * torch.randn(2, 3, 7, dtype=DT, generator=gen)).requires_grad_(True)
    chi = basis(q)
    assert chi.shape == (2, 3, 3, 7) and chi.dtype == DT
    K = basis.K().detach()
    for i in range(basis.M):
        d = q - basis.eta.detach()[i]
        G = torch.exp(-0.5 * torch.einsum("...a,ab,...b->...", d, K[i], d))
        (grad,) = torch.autograd.grad(G.sum(), q)
        assert float((chi[..., i, :].detach() - grad).abs().max()) <= 1e-14
    assert float(chi.detach().abs().max()) > 0.05  # the fields are not negligible at these points


def test_basis_gradcheck(gen):
    basis = _basis(gen, M=2)
    q = (basis.eta.detach()[0] + 0.3 * torch.randn(2, 7, dtype=DT, generator=gen)).requires_grad_(True)
    eta = basis.eta.detach().clone().requires_grad_(True)
    raw = basis.stiffness.raw.detach().clone().requires_grad_(True)

    def f(q, eta, raw):
        return functional_call(basis, {"eta": eta, "stiffness.raw": raw}, (q,))

    assert gradcheck(f, (q, eta, raw))


def test_modules_are_float64_and_convert_with_to(gen):
    eta = torch.randn(2, 7, generator=gen).float()
    K = torch.eye(7).expand(2, 7, 7).float()
    basis = FieldBasis(eta, K, kind="diag")
    assert basis.eta.dtype == torch.float64
    assert basis(torch.zeros(7, dtype=torch.float64)).dtype == torch.float64
    w = MotionWeights(torch.tensor([[3.0, 0.0]]), torch.tensor([[0.0, 1.0]]), torch.tensor([3.0]))
    assert w.a.dtype == torch.float64
    assert torch.allclose(FieldProgram(basis, w)(torch.tensor(1.0), torch.zeros(1, 7, dtype=torch.float64)),
                          FieldProgram(basis, w)(1.0, torch.zeros(1, 7, dtype=torch.float64)))
    b32 = basis.float()
    assert b32(torch.zeros(7)).dtype == torch.float32


# ------------------------------------------------------------------------- weights

def test_weights_non_negative_and_projection(gen):
    a = _t([[1.0, -0.5, 0.2], [0.0, 2.0, -3.0]])
    b = _t([[-1.0, 0.5, 0.2], [0.3, -2.0, 1.0]])
    w = MotionWeights(a, b, duration=_t([1.0, 2.0]))
    assert bool((w.a_raw >= 0).all()) and bool((w.b_raw >= 0).all())  # projected at init
    assert torch.equal(w.a, a.clamp(min=0)) and torch.equal(w.b, b.clamp(min=0))
    with torch.no_grad():
        w.a_raw.copy_(a)
        w.b_raw.copy_(b)
        w.step_duration[0, 0] = -1.0
        w.pulse_duration[1, 2] = 1e-4
    assert float(w.a_raw.detach().min()) < 0                    # stored values may go negative
    assert torch.equal(w.a, a.clamp(min=0)) and torch.equal(w.b, b.clamp(min=0))  # read ≥ 0
    w.project_(min_duration=0.05)
    assert torch.equal(w.a_raw.detach(), a.clamp(min=0))
    assert torch.equal(w.b_raw.detach(), b.clamp(min=0))
    assert float(w.step_duration.detach()[0, 0]) == 0.05 and float(w.pulse_duration.detach()[1, 2]) == 0.05
    # The defaults: onsets 0, durations λ of the motion.
    assert torch.equal(w.step_onset.detach(), torch.zeros(2, 3, dtype=DT))
    assert torch.equal(w.pulse_duration.detach()[0], torch.ones(3, dtype=DT))


def _weights(gen, N=2, M=3):
    a = torch.rand(N, M, dtype=DT, generator=gen) + 0.1
    b = torch.rand(N, M, dtype=DT, generator=gen) + 0.1
    s = 0.3 * torch.rand(N, M, dtype=DT, generator=gen)
    d = 0.5 + torch.rand(N, M, dtype=DT, generator=gen)
    p = 0.3 * torch.rand(N, M, dtype=DT, generator=gen)
    e = 0.5 + torch.rand(N, M, dtype=DT, generator=gen)
    w = MotionWeights(a, b, duration=_t([1.0, 1.5][:N]), step_onset=s, step_duration=d,
                        pulse_onset=p, pulse_duration=e)
    return w, (a, b, s, d, p, e)


@torch.no_grad()
def test_activation_matches_hand_computation(gen):
    w, (a, b, s, d, p, e) = _weights(gen)
    times = [-0.2, 0.0, 0.1, 0.37, 0.8, 1.2, 3.0]
    for t in times:
        act = w.activation(t)
        assert act.shape == (2, 3)
        for j in range(2):
            for i in range(3):
                ref = (float(a[j, i]) * psi_ref((t - float(s[j, i])) / float(d[j, i]))
                       + float(b[j, i]) * phi_ref((t - float(p[j, i])) / float(e[j, i])))
                assert float(act[j, i]) == pytest.approx(ref, rel=1e-14, abs=1e-15)
    # Before every onset nothing is active; long after, only the steps (value a) remain.
    assert float(w.activation(-0.1).abs().max()) == 0.0
    assert torch.allclose(w.activation(10.0), a, rtol=0, atol=1e-15)


@torch.no_grad()
def test_profiles_over_time_vector(gen):
    w, _ = _weights(gen)
    t = torch.linspace(-0.5, 2.0, 11, dtype=DT)
    psi, phi = w.profiles(t)
    assert psi.shape == (11, 2, 3) and phi.shape == (11, 2, 3)
    act = w.activation(t)
    assert act.shape == (11, 2, 3)
    for k in range(11):
        ps, ph = w.profiles(t[k])
        assert torch.equal(psi[k], ps) and torch.equal(phi[k], ph)
        assert float((act[k] - w.activation(t[k])).abs().max()) <= 1e-15


# ------------------------------------------------------------------------- program

@torch.no_grad()
def test_program_is_weighted_sum_of_fields(gen):
    basis = _basis(gen, M=3)
    w, _ = _weights(gen, N=2, M=3)
    program = FieldProgram(basis, w)
    q = basis.eta.detach()[0] + 0.5 * torch.randn(5, 2, 7, dtype=DT, generator=gen)
    v = torch.randn(5, 2, 7, dtype=DT, generator=gen)
    t = _t(0.4)
    tau = program(t, q, v)
    assert tau.shape == (5, 2, 7)
    act = w.activation(t)
    ref = torch.zeros(5, 2, 7, dtype=DT)
    for j in range(2):
        for i in range(3):
            ref[:, j] += act[j, i] * basis(q[:, j])[:, i]
    assert float((tau - ref).abs().max()) <= 1e-14
    assert float(ref.abs().max()) > 0.05
    # Fields do not depend on v; the program ignores it.
    assert torch.equal(program(t, q, torch.zeros_like(v)), tau)
    # index= picks motions: row j of the result is motion index[j].
    single = FieldProgram(basis, w, index=[1])
    assert float((single(t, q[:, 1:2], v[:, 1:2]) - tau[:, 1:2]).abs().max()) <= 1e-15
    swapped = FieldProgram(basis, w, index=[1, 0])
    tau_sw = swapped(t, q.flip(-2), v)
    assert float((tau_sw - tau.flip(-2)).abs().max()) <= 1e-15
    # Motion 0's weights on motion 1's coordinates give something else (index matters).
    assert float((FieldProgram(basis, w, index=[0])(t, q[:, 1:2]) - tau[:, 1:2]).abs().max()) > 1e-3


@pytest.mark.parametrize("kind", ["scalar", "diag", "block", "full"])
def test_project_bounds_stiffness_and_centres(kind):
    K = torch.stack([1e4 * torch.eye(7, dtype=torch.float64), 1e-5 * torch.eye(7, dtype=torch.float64)])
    basis = FieldBasis(torch.full((2, 7), 50.0, dtype=torch.float64), K, kind=kind, blocks=[3, 1, 3])
    basis.project_()
    eig = torch.linalg.eigvalsh(basis.K().detach())
    lo, hi = K_RANGE
    assert eig.min() >= lo * (1 - 1e-12) and eig.max() <= 7 * hi
    assert torch.allclose(torch.diagonal(basis.K().detach(), dim1=-2, dim2=-1)[0],
                          torch.full((7,), hi, dtype=torch.float64))
    assert float(basis.eta.detach().abs().max()) == pytest.approx(ETA_MAX)


def test_random_programs_with_diagonal_stiffness():
    """random_gestures(stiffness="diag"): seven per-axis stiffnesses per field, each within
    SUPPORTED["k"]; the option changes only the stiffness draws, and the scalar programs
    stay those the documented bar was measured on (seed 2024); library_model turns them
    into a diag basis with K = diag(k), and a wrong-length entry is refused."""
    from tflearn.data import gestures
    lo, hi = gestures.SUPPORTED["k"]
    diag = gestures.random_gestures(6, seed=3, stiffness="diag")
    assert [p.name for p in diag] == [f"random3d_{i}" for i in range(6)]
    ks = [k for p in diag for k in p.k]
    assert all(len(k) == 7 and all(lo <= x <= hi for x in k) for k in ks)
    assert max(max(k) / min(k) for k in ks) > 2          # really per axis, not k·I
    scalar = gestures.random_gestures(6, seed=3)
    assert all(isinstance(k, float) for p in scalar for k in p.k)
    assert diag[0].eta == scalar[0].eta and diag[0].k[0][0] == scalar[0].k[0]
    assert gestures.random_gestures(1, seed=2024)[0].k == (1.1219106600829352,)
    basis, _, _ = gestures.library_model(diag)
    assert basis.kind == "diag"
    assert torch.allclose(basis.K().detach(), torch.diag_embed(torch.tensor(ks, dtype=torch.float64)),
                          rtol=1e-14, atol=0)
    assert gestures.library_model(scalar)[0].kind == "scalar"
    with pytest.raises(ValueError, match="needs 7 values, got 3"):
        gestures.stiffness_matrix((1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match="stiffness must be one of"):
        gestures.random_gestures(1, stiffness="block")


def test_random_programs_with_full_stiffness():
    """random_gestures(stiffness="full"): K = Q diag(k) Qᵀ, symmetric, its seven
    eigenvalues within SUPPORTED["k"] and its axes coupling the coordinates; the centres
    are the scalar programs' (the same draws); library_model makes a full basis holding
    each K, and a matrix of the wrong shape is refused."""
    from tflearn.data import gestures
    lo, hi = gestures.SUPPORTED["k"]
    full = gestures.random_gestures(6, seed=3, stiffness="full")
    assert [p.name for p in full] == [f"random3f_{i}" for i in range(6)]
    Ks = torch.stack([gestures.stiffness_matrix(k) for p in full for k in p.k])
    assert torch.equal(Ks, Ks.transpose(-1, -2))
    eig = torch.linalg.eigvalsh(Ks)
    assert float(eig.min()) >= lo - 1e-12 and float(eig.max()) <= hi + 1e-12
    off = Ks - torch.diag_embed(torch.diagonal(Ks, dim1=-2, dim2=-1))
    assert float(off.abs().amax((-1, -2)).min()) > 0.1          # coupled, not diagonal
    assert full[0].eta == gestures.random_gestures(6, seed=3)[0].eta
    basis, _, _ = gestures.library_model(full)
    assert basis.kind == "full"
    assert torch.allclose(basis.K().detach(), Ks, rtol=0, atol=1e-13)
    with pytest.raises(ValueError, match="needs 7 rows of 7 values"):
        gestures.stiffness_matrix(((1.0,) * 6,) * 7)


@pytest.mark.parametrize("stiffness", ["scalar", "diag"])
def test_random_programs_over_a_shared_library(stiffness):
    """random_gestures(library=G): every program's one or two fields are distinct members
    of one set of G fields drawn within SUPPORTED, each program with its own weights and
    duration; 40 programs use every one of the G = 5 and both sizes; library = 0 keeps
    the programs of own fields, and a negative library is refused."""
    from tflearn.data import gestures
    programs = gestures.random_gestures(40, seed=4, stiffness=stiffness, library=5)
    tag = "dL5" if stiffness == "diag" else "L5"
    assert [p.name for p in programs] == [f"random4{tag}_{i}" for i in range(40)]
    fields = [(e, k) for p in programs for e, k in zip(p.eta, p.k)]
    assert len(set(fields)) == 5
    assert all(len(set(zip(p.eta, p.k))) == len(p.eta) for p in programs)
    assert {len(p.eta) for p in programs} == {1, 2}
    lo, hi = gestures.SUPPORTED["duration"]
    assert len({p.duration for p in programs}) > 10 and all(lo <= p.duration <= hi for p in programs)
    assert len({p.a[0] for p in programs}) == 40
    own = gestures.random_gestures(40, seed=4, stiffness=stiffness)
    assert len({(e, k) for p in own for e, k in zip(p.eta, p.k)}) == sum(len(p.eta) for p in own)
    with pytest.raises(ValueError, match="library must be ≥ 0"):
        gestures.random_gestures(1, library=-1)


@pytest.mark.parametrize("stiffness", ["scalar", "diag"])
def test_own_fields_program_gives_the_library_programs_torques(stiffness):
    """gestures.own_fields_program evaluates each motion's own fields only; its torques are
    the whole library program's, bit for bit, at a scalar time, sample times and a time
    per member."""
    from tflearn.data import gestures
    programs = gestures.random_gestures(5, seed=11, stiffness=stiffness)
    basis, weights, spans = gestures.library_model(programs)
    assert basis.M == sum(hi - lo for lo, hi in spans) > max(hi - lo for lo, hi in spans)
    whole, own = FieldProgram(basis, weights), gestures.own_fields_program(basis, weights, spans)
    gen = torch.Generator().manual_seed(0)
    q = torch.randn(4, 5, basis.n, generator=gen, dtype=torch.float64)
    v = torch.randn(4, 5, basis.n, generator=gen, dtype=torch.float64)
    for t in (torch.tensor(0.4, dtype=torch.float64), torch.linspace(0, 1, 4, dtype=torch.float64),
              torch.rand(4, 5, generator=gen, dtype=torch.float64)):
        ref = whole(t, q, v)
        assert ref.abs().max() > 1e-3 and torch.equal(own(t, q, v), ref)
