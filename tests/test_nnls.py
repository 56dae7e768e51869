"""tflearn.fit.nnls: batched Lawson–Hanson NNLS against scipy.optimize.nnls, and the KKT
conditions of its solutions.

Accuracy note. tflearn solves the normal equations G = AᵀA, h = Aᵀy, whose condition
number is cond(A)², and adds a ridge of ``ridge`` × max diag(G) (default 1e-12) on the
passive set, which moves the solution by about cond(G)·ridge relative. Measured against
scipy (max |x − x_scipy| / max(1, max |x_scipy|), batches of 12 problems):

* Gaussian A (cond ≲ 10): 4.4e-12 with the default ridge; exact non-negative
  solutions: 1.1e-11;
* cond(A) = 1e2 (singular values log-spaced over two decades): 8.5e-9 with the
  default ridge, 8.9e-13 with ``ridge=0``;
* cond(A) = 1e3: 1.0e-6 with the default ridge (that is the ridge, not the active
  set: with ``ridge=0`` it is 4.7e-11), so the 1e-9 comparison there uses ``ridge=0``.
"""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.optimize as so
import torch

from tflearn.fit.nnls import (
    NNLSError,
    NNLSResult,
    NNLSWarning,
    nnls,
    nnls_lstsq,
    packed,
    take,
    warn_unconverged,
)

BATCH = (3, 4)


def _orthonormal(rng, m, k):
    return np.linalg.qr(rng.normal(size=(m, k)))[0]


def make_problem(rng, kind: str, k: int):
    """One (A (m×k), y (m)) of a kind; m = 2k + 6."""
    m = 2 * k + 6
    if kind == "well":
        A = rng.normal(size=(m, k))
        y = rng.normal(size=m)
    elif kind in ("ill100", "ill1000"):
        cond = 1e2 if kind == "ill100" else 1e3
        s = np.logspace(0, -np.log10(cond), k)
        A = (_orthonormal(rng, m, k) * s) @ _orthonormal(rng, k, k).T
        y = rng.normal(size=m)
    elif kind == "negative":
        # Every column has a positive inner product with every other and a negative
        # one with y: the unconstrained descent direction is negative everywhere → x = 0.
        A = np.abs(rng.normal(size=(m, k))) + 0.1
        y = -np.abs(rng.normal(size=m)) - 0.1
    elif kind == "exact":
        A = rng.normal(size=(m, k))
        x = np.abs(rng.normal(size=k)) + 0.1
        x[rng.random(k) < 0.3] = 0.0
        y = A @ x
    else:
        raise KeyError(kind)
    return A, y


def batch_problem(rng, kind, k):
    probs = [make_problem(rng, kind, k) for _ in range(int(np.prod(BATCH)))]
    A = np.stack([p[0] for p in probs]).reshape(BATCH + probs[0][0].shape)
    y = np.stack([p[1] for p in probs]).reshape(BATCH + probs[0][1].shape)
    return A, y


def scipy_nnls(A, y):
    m, k = A.shape[-2:]
    xs = [so.nnls(a, b, maxiter=50 * k)[0] for a, b in zip(A.reshape(-1, m, k), y.reshape(-1, m))]
    return np.stack(xs).reshape(A.shape[:-2] + (k,))


def rel_err(x, ref):
    """max |x − ref| / max(1, max |ref|) per problem (max over the batch)."""
    scale = np.maximum(1.0, np.abs(ref).max(-1))
    return float((np.abs(x - ref).max(-1) / scale).max())


def kkt_violation(G, h, x):
    """(min x, max |g| on the positive set, min g on the zero set), g = Gx − h, all
    relative to max |h| per problem."""
    g = np.einsum("...ij,...j->...i", G, x) - h
    scale = np.abs(h).max(-1, keepdims=True) + 1e-300
    g = g / scale
    pos = x > 0
    g_pos = np.where(pos, np.abs(g), 0.0).max()
    g_zero = np.where(~pos, g, np.inf).min()
    return float(x.min()), float(g_pos), float(g_zero)


KS = [1, 2, 3, 5, 8, 12, 16]


@pytest.mark.parametrize("k", KS)
@pytest.mark.parametrize("kind,ridge,tol", [
    ("well", None, 1e-10),
    ("ill100", None, 3e-8),
    ("ill100", 0.0, 1e-11),
    ("ill1000", 0.0, 1e-9),
    ("negative", None, 0.0),
    ("exact", None, 1e-10),
])
def test_matches_scipy(kind, ridge, tol, k):
    rng = np.random.default_rng(1000 * k + sum(map(ord, kind)))
    A, y = batch_problem(rng, kind, k)
    kw = {} if ridge is None else {"ridge": ridge}
    sol = nnls_lstsq(torch.from_numpy(A), torch.from_numpy(y), **kw)
    assert isinstance(sol, NNLSResult) and sol.converged.shape == BATCH
    assert bool(sol.converged.all()) and 0 <= sol.iterations <= 3 * k + 10
    x = sol.x
    assert x.shape == BATCH + (k,) and x.dtype == torch.float64
    x = x.numpy()
    ref = scipy_nnls(A, y)
    assert rel_err(x, ref) <= tol
    if kind == "negative":
        assert np.all(ref == 0.0) and np.all(x == 0.0)
    if kind == "exact":
        # The exact non-negative solution is unique (A has full column rank): both find it.
        x_true = np.linalg.lstsq(A.reshape(-1, *A.shape[-2:])[0], y.reshape(-1, y.shape[-1])[0],
                                 rcond=None)[0]
        assert np.abs(x.reshape(-1, k)[0] - x_true).max() <= 1e-10 * max(1, np.abs(x_true).max())
        # and the fit is exact
        r = np.einsum("...mk,...k->...m", A, x) - y
        assert np.abs(r).max() <= 1e-10 * np.abs(y).max()


@pytest.mark.parametrize("kind", ["well", "ill100", "negative", "exact"])
def test_kkt(kind):
    """x ≥ 0; the gradient g = Gx − h vanishes on the positive set and is ≥ 0 on the zeros."""
    rng = np.random.default_rng(7 + len(kind))
    for k in (4, 16):
        A, y = batch_problem(rng, kind, k)
        G = np.swapaxes(A, -1, -2) @ A
        h = np.einsum("...mk,...m->...k", A, y)
        x = nnls(torch.from_numpy(G), torch.from_numpy(h)).x.numpy()
        xmin, g_pos, g_zero = kkt_violation(G, h, x)
        assert xmin >= 0.0
        assert g_pos <= (1e-8 if kind == "ill100" else 1e-11)
        assert g_zero >= -1e-11


def test_mixed_active_sets():
    """A batch where the problems have every possible number of active constraints, in
    one lock-step solve: each agrees with its own scipy solution."""
    rng = np.random.default_rng(3)
    k, m = 6, 20
    As, ys, n_pos = [], [], []
    for j in range(k + 1):
        A = rng.normal(size=(m, k))
        x = np.zeros(k)
        x[rng.permutation(k)[:j]] = rng.uniform(0.5, 2.0, size=j)
        # KKT by construction: Aᵀ(Ax − y) = λ with λ = 0 on the support of x and λ > 0
        # off it, i.e. y = A(x − G⁻¹λ) + (a component orthogonal to the range of A).
        lam = np.where(x > 0, 0.0, rng.uniform(0.5, 2.0, size=k))
        Q = np.linalg.qr(A)[0]
        null = rng.normal(size=m)
        null -= Q @ (Q.T @ null)
        y = A @ (x - np.linalg.solve(A.T @ A, lam)) + null
        As.append(A)
        ys.append(y)
        n_pos.append(j)
    A, y = np.stack(As), np.stack(ys)
    x = nnls_lstsq(torch.from_numpy(A), torch.from_numpy(y)).x.numpy()
    ref = scipy_nnls(A, y)
    assert rel_err(x, ref) <= 1e-10
    assert [int((xi > 0).sum()) for xi in x] == n_pos


def test_packed_takes_each_rows_indices_in_order():
    """packed: each row's True indices first, in order, padded to the most any row has;
    take: those rows and columns of G and entries of h, 0 in the padding."""
    mask = torch.tensor([[False, True, False, True], [True, False, False, False], [False] * 4])
    cols, pad = packed(mask)
    assert cols[:, :2].tolist()[0] == [1, 3] and cols[1, 0] == 0
    assert pad.tolist() == [[False, False], [False, True], [True, True]]
    G = torch.arange(48.0).reshape(3, 4, 4)
    h = torch.arange(12.0).reshape(3, 4)
    Gp, hp = take(G, h, cols, pad)
    assert Gp[0].tolist() == [[5.0, 7.0], [13.0, 15.0]] and hp[0].tolist() == [1.0, 3.0]
    assert Gp[1].tolist() == [[16.0, 0.0], [0.0, 0.0]] and hp[1].tolist() == [4.0, 0.0]
    assert float(Gp[2].abs().max()) == 0.0 and float(hp[2].abs().max()) == 0.0


def test_passive_solves_are_the_size_of_the_passive_set(monkeypatch):
    """Three problems of 40 unknowns whose optimum has 3 positive entries: x is that
    optimum, and no linear solve on the way is larger than the passive set grew (≤ 6),
    not 40×40."""
    gen = torch.Generator().manual_seed(4)
    k = 40
    A = torch.randn(3, 60, k, generator=gen, dtype=torch.float64)
    G = A.transpose(-1, -2) @ A
    x_true = torch.zeros(3, k, dtype=torch.float64)
    for b, idx in enumerate(([0, 7, 30], [5, 6, 39], [12, 20, 21])):
        x_true[b, idx] = torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
    h = (G @ x_true.unsqueeze(-1)).squeeze(-1)
    sizes, solve = [], torch.linalg.solve
    monkeypatch.setattr(torch.linalg, "solve", lambda a, b: sizes.append(a.shape[-1]) or solve(a, b))
    res = nnls(G, h)
    assert bool(res.converged.all())
    torch.testing.assert_close(res.x, x_true, rtol=1e-9, atol=1e-10)
    print("passive system sizes:", sorted(set(sizes)))
    assert 3 <= max(sizes) <= 6


def test_shared_G_broadcasts():
    """G (k×k) shared by a batch of h (3×4×k): same as solving each separately."""
    rng = np.random.default_rng(11)
    k = 8
    A = rng.normal(size=(30, k))
    Y = rng.normal(size=BATCH + (30,))
    G = A.T @ A
    H = Y @ A
    x = nnls(torch.from_numpy(G), torch.from_numpy(H)).x.numpy()
    assert x.shape == BATCH + (k,)
    ref = np.stack([so.nnls(A, yy)[0] for yy in Y.reshape(-1, 30)]).reshape(BATCH + (k,))
    assert rel_err(x, ref) <= 1e-10
    assert 0 < (x > 0).sum() < x.size          # both active and inactive constraints occur


def test_rank_deficient():
    """Duplicate and zero columns (singular G): the solution is not unique, but the
    objective equals scipy's and the KKT conditions hold."""
    rng = np.random.default_rng(5)
    k = 8
    A = rng.normal(size=BATCH + (25, k))
    A[..., 3] = A[..., 1]          # duplicate column
    A[..., 5] = 0.0                # a field that never acts
    y = rng.normal(size=BATCH + (25,))
    x = nnls_lstsq(torch.from_numpy(A), torch.from_numpy(y)).x.numpy()
    ref = scipy_nnls(A, y)

    def obj(z):
        return ((np.einsum("...mk,...k->...m", A, z) - y) ** 2).sum(-1)
    assert np.all(np.isfinite(x)) and x.min() >= 0.0
    assert np.abs(obj(x) - obj(ref)).max() <= 1e-10 * np.abs(obj(ref)).max()
    assert np.all(x[..., 5] == 0.0)
    G = np.swapaxes(A, -1, -2) @ A
    h = np.einsum("...mk,...m->...k", A, y)
    _, g_pos, g_zero = kkt_violation(G, h, x)
    assert g_pos <= 1e-9 and g_zero >= -1e-11


def test_a_column_of_subnormal_norm_takes_no_weight():
    """Element 0: the normal equations of a field whose Gaussian is 1e-155 on a motion's
    path (step and pulse columns, as a thousand-motion run met them, and a zero column):
    G's entries are subnormal, and the passive solve on them gave NaN. Element 1: two ordinary columns
    and such a third, collinear with the first. Either way the tiny column gets no
    weight, the solve converges, and element 1 ends on the two-column solution."""
    G = torch.zeros(2, 3, 3, dtype=torch.float64)
    h = torch.zeros(2, 3, dtype=torch.float64)
    G[0, :2, :2] = torch.tensor([[1.0140830235606e-310, 3.024514516677e-312],
                                  [3.024514516677e-312, 9.0206518676e-314]], dtype=torch.float64)
    h[0, :2] = torch.tensor([7.423267936631363e-159, 2.2136323875591635e-160],
                           dtype=torch.float64)
    A = torch.tensor([[1.0, 0.2], [0.3, 1.0], [0.5, 0.4]], dtype=torch.float64)
    y = torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
    tiny = 1e-155 * A[:, :1]
    A3 = torch.cat([A, tiny], 1)
    G[1], h[1] = A3.T @ A3, A3.T @ y
    res = nnls(G, h)
    assert torch.isfinite(res.x).all() and res.converged.tolist() == [True, True]
    assert res.x[0].tolist() == [0.0, 0.0, 0.0] and res.x[1, 2] == 0.0
    two = nnls(A.T @ A, A.T @ y).x
    torch.testing.assert_close(res.x[1, :2], two, rtol=1e-12, atol=0)
    assert float(two.min()) > 0


def test_zero_rhs_and_not_differentiable():
    """h = 0 → x = 0; the solve runs under no_grad (the envelope theorem needs no dx*/dθ)."""
    G = torch.eye(4, dtype=torch.float64).expand(2, 4, 4).clone().requires_grad_(True)
    h = torch.zeros(2, 4, dtype=torch.float64)
    x = nnls(G, h).x
    assert torch.equal(x, torch.zeros(2, 4, dtype=torch.float64))
    assert not x.requires_grad
    # A diagonal G: x_i = max(h_i, 0) / G_ii exactly.
    d = torch.tensor([1.0, 2.0, 4.0, 0.5], dtype=torch.float64)
    h2 = torch.tensor([[1.0, -1.0, 2.0, 3.0]], dtype=torch.float64)
    x2 = nnls(torch.diag(d)[None], h2).x
    torch.testing.assert_close(x2, torch.tensor([[1.0, 0.0, 0.5, 6.0]], dtype=torch.float64),
                               rtol=1e-11, atol=0)


def hard_and_easy():
    """A batch of two k = 3 problems with G = I: h = (1, 2, 3) needs 3 outer iterations
    (x = h), h = (−1, 2, −3) one (x = (0, 2, 0))."""
    G = torch.eye(3, dtype=torch.float64)
    h = torch.tensor([[1.0, 2.0, 3.0], [-1.0, 2.0, -3.0]], dtype=torch.float64)
    return G, h


def test_convergence_is_reported_per_element():
    G, h = hard_and_easy()
    short = nnls(G, h, max_iter=1)
    assert short.converged.tolist() == [False, True] and short.iterations == 1
    torch.testing.assert_close(short.x[1], torch.tensor([0.0, 2.0, 0.0], dtype=torch.float64))
    full = nnls(G, h)
    assert full.converged.tolist() == [True, True] and full.iterations == 3
    torch.testing.assert_close(full.x, h.clamp_min(0))


def test_throw_raises_naming_the_count():
    G, h = hard_and_easy()
    with pytest.raises(NNLSError, match="did not converge for 1 of 2 problem"):
        nnls(G, h, max_iter=2, throw=True)
    assert bool(nnls(G, h, throw=True).converged.all())
    assert issubclass(NNLSError, ArithmeticError)


def test_nan_input_is_not_converged():
    """A NaN in h never frees an index, so the loop stops at once; it must not pass for
    converged."""
    G, h = hard_and_easy()
    h[0, 1] = float("nan")
    assert nnls(G, h).converged.tolist() == [False, True]


def test_warn_unconverged_names_the_elements():
    G, h = hard_and_easy()
    with pytest.warns(NNLSWarning, match=r"^fit: NNLS did not converge for hard after 1 "):
        warn_unconverged(nnls(G, h, max_iter=1), ["hard", "easy"], "fit")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_unconverged(nnls(G, h), ["hard", "easy"], "fit")
