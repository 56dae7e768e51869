"""The thesis' SLSQP baseline (tflearn.fit.slsqp) on the "come here" gesture."""
from __future__ import annotations

import pytest
import torch

from tflearn.data import gestures
from tflearn.fit import slsqp, torque
from tflearn.fit.targets import prepare
from tflearn.model.fields import FieldBasis
from tflearn.model.weights import MotionWeights
from tflearn.physics import body as tb

DT = torch.float64


@pytest.fixture(scope="module")
def come_here():
    torch.set_num_threads(1)
    body = tb.arm()
    (motion, lb), = gestures.generate(body, gestures=[gestures.GESTURES["come_here"]])
    return prepare(body, [motion]), lb


def noised(lb, seed: int, r: float):
    """The true parameters, each (every η entry, k, a, b) times a factor in [1, r]."""
    g = torch.Generator().manual_seed(seed)

    def f(x):
        return x * (1 + (r - 1) * torch.rand(x.shape, generator=g, dtype=DT))
    eta = f(lb.basis.eta.detach())
    k = f(torch.diagonal(lb.basis.K().detach(), dim1=-2, dim2=-1)[:, :1])
    n = eta.shape[1]
    basis = FieldBasis(eta, k[..., None] * torch.eye(n, dtype=DT), kind="diag")
    weights = MotionWeights(f(lb.weights.a.detach()), f(lb.weights.b.detach()),
                            lb.weights.duration)
    return basis, weights


def test_cost_matches_torque_cost(come_here):
    """The SLSQP objective is torque.torque_cost for a diagonal K (phases included)."""
    tg, _ = come_here
    g = torch.Generator().manual_seed(3)
    M, n = 2, 7
    eta = torch.randn(M, n, generator=g, dtype=DT)
    k = 0.5 + 2 * torch.rand(M, n, generator=g, dtype=DT)
    a, b = torch.rand(1, M, generator=g, dtype=DT), torch.rand(1, M, generator=g, dtype=DT)
    weights = MotionWeights(a, b, tg.duration, pulse_onset=torch.full((1, M), 0.2, dtype=DT),
                            step_duration=torch.full((1, M), 2.0, dtype=DT))
    basis = FieldBasis(eta, torch.diag_embed(k), kind="diag")
    cost = slsqp.cost_function(weights, tg, M, n)(slsqp.pack(eta, k, a, b))
    with torch.no_grad():
        ref = torque.torque_cost(basis, weights, tg)
    torch.testing.assert_close(cost, ref, rtol=1e-12, atol=1e-15)


def test_from_truth_stays_at_zero(come_here):
    tg, lb = come_here
    res = slsqp.fit_slsqp(lb.basis, lb.weights, tg)
    assert res["initial_cost"] < 1e-9                       # measured 7.8e-11 (spline torques)
    assert res["cost"] <= res["initial_cost"] * (1 + 1e-9)
    assert res["success"]
    assert res["kind"] == "diag"                            # a scalar basis comes back diag
    torch.testing.assert_close(res["basis"].eta.detach(), lb.basis.eta.detach(), atol=1e-6, rtol=0)
    torch.testing.assert_close(res["basis"].K().detach(), lb.basis.K().detach(), atol=1e-5, rtol=0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_from_noised_truth(come_here, seed):
    """From the truth times factors in [1, 1.2], SLSQP drives the cost down by orders of
    magnitude (measured, seeds 0–9: from 9e-3..2e-1 to 7.8e-11, the truth's own cost) and keeps
    the constraints."""
    tg, lb = come_here
    basis, weights = noised(lb, seed, 1.2)
    res = slsqp.fit_slsqp(basis, weights, tg)
    assert res["initial_cost"] > 1e-3
    assert res["cost"] < 1e-3 * res["initial_cost"]
    assert res["cost"] < 1e-8
    assert res["success"], res["message"]
    nb, nw = res["basis"], res["weights"]
    assert bool((nw.a_raw >= 0).all()) and bool((nw.b_raw >= 0).all())
    K = nb.K().detach()
    assert bool((torch.diagonal(K, dim1=-2, dim2=-1) > 0).all())
    assert bool((K == torch.diag_embed(torch.diagonal(K, dim1=-2, dim2=-1))).all())
    assert res["nfev"] > res["nit"] * (2 * 7 + 2)           # forward differences: ≥ 1 per parameter
    with torch.no_grad():
        assert float(torque.torque_cost(nb, nw, tg).sum()) == pytest.approx(res["cost"], rel=1e-9)
    # the recovered field is the generating one
    torch.testing.assert_close(nb.eta.detach(), lb.basis.eta.detach(), atol=1e-3, rtol=0)
    assert float(nw.a.detach()[0, 0]) == pytest.approx(3.0, rel=1e-3)
    # the input modules are left alone
    assert bool((basis.eta != nb.eta).any())


def test_inplace(come_here):
    tg, lb = come_here
    basis, weights = noised(lb, 5, 1.1)
    seen = []
    res = slsqp.fit_slsqp(basis, weights, tg, max_iter=5, inplace=True,
                          callback=lambda it, cost: seen.append(cost))
    assert res["nit"] <= 5 and len(seen) == res["nit"]
    assert seen[-1] == pytest.approx(res["cost"], rel=1e-12)
    torch.testing.assert_close(basis.K(), res["basis"].K())
    torch.testing.assert_close(weights.a, res["weights"].a)
    with pytest.raises(ValueError):
        slsqp.fit_slsqp(lb.basis, lb.weights, tg, inplace=True)    # a scalar basis
