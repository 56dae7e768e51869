"""A spanning layout of fields for motions no field made (recorded, keyframed).

Greedy growth (:mod:`tflearn.fit.search`) adds the one field that best explains what is
left, and stops when the next one gains little. On recorded motion that ends after one
or two fields whose torques point along one or two directions, while a 7-dof arm's
torques turn through all seven. A basis whose fields *positively span* joint space
everywhere along the paths needs no search: with 2n fields around the motions' mean
posture ν̄, one on each side of every coordinate,

    η_{±k} = ν̄ ± r e_k,        K_{±k} = κ diag(m̄_1 … m̄_n),

every torque direction at every posture within r of ν̄ (|ν − ν̄|∞ < r) is a
non-negative combination of the fields (near ν̄ a field is the spring −K(ν − η), and the
pair ±k pushes both ways along e_k; beyond ν̄ ± r e_k both push the same way), so the
weights — step, pulse and P sub-movement windows per field — come from one exact NNLS
solve, and multiple shooting then fits them to the paths. m̄ is the mean
joint-space inertia along the motions (:func:`~tflearn.fit.targets.mean_inertia`), so κ
is a squared frequency (1/s²) and a unit activation drives every coordinate at the same
rate: the light wrist is not made a thousand times stiffer than the shoulder (which
turns the simulation stiff), and each field's Gaussian is widest where the inertia is
smallest. With r e_k far from the path in K's metric the fields are nearly linear
springs along the motions, their activations co-contract, and any co-activation adds
stiffness and damping (ζK) about the path — the fields' feedback that open-loop torque
matching lacks.
"""
from __future__ import annotations

import warnings

import torch

from ..body import Body
from ..fields import FieldBasis
from .targets import Targets, mean_inertia


def spanning_basis(body: Body, tg: Targets, template: FieldBasis, radius: float = 2.0,
                   stiffness: float = 1.0) -> FieldBasis:
    """2n fields like ``template`` (its kind must hold a diagonal K: not ``scalar``; its
    damping ratio is kept) at ν̄ ± ``radius`` e_k, K = ``stiffness`` · diag(m̄), ν̄ and m̄
    the mean posture and mean inertia over every real sample of the motions in ``tg``
    (module docstring). Warns when a motion leaves the box |ν − ν̄|∞ < ``radius``, where
    the fields no longer push every way."""
    if template.kind == "scalar":
        raise ValueError("spanning_basis: the layout's stiffness is per coordinate; "
                         "it needs model.stiffness diag, block or full, not scalar")
    real = tg.mask.unsqueeze(-1).to(tg.q.dtype)
    centre = (tg.q * real).sum((0, 1)) / real.sum((0, 1))                      # n
    samples = tg.mask.sum(-1, keepdim=True).to(tg.q.dtype)                    # N×1
    inertia = (mean_inertia(body, tg) * samples).sum(0) / samples.sum()      # n
    far = ((tg.q - centre).abs().amax(-1) * tg.mask).amax(-1)               # N
    if float(far.max()) >= radius:
        j = int(far.argmax())
        warnings.warn(f"layout: motion {tg.names[j]} reaches {float(far[j]):.2f} rad from the "
                      f"motions' mean posture in one coordinate, beyond the fields' radius "
                      f"{radius:g} rad, where they cannot push every way: raise "
                      f"solver.layout.radius", stacklevel=2)
    n = centre.shape[0]
    eye = torch.eye(n, dtype=torch.float64)
    eta = torch.cat([centre + radius * eye, centre - radius * eye])
    K = (stiffness * torch.diag(inertia)).expand(2 * n, n, n).clone()
    return template.like(eta, K)
