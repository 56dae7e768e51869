"""Torque fields (thesis §3.2): the shared basis of fields a motion's torque program weights.

A field i is the gradient of a Gaussian over coordinates ν (n = nv):

    χ_i(ν) = −K_i (ν − η_i) · exp(−½ (ν − η_i)ᵀ K_i (ν − η_i))

with K_i positive definite by construction in one of four kinds: ``scalar`` (k·I),
``diag``, ``block`` (one full block per joint, e.g. 3×3, 1×1, 3×3 for the arm) or ``full``
(K = L Lᵀ with L lower triangular and a positive diagonal). With a damping ratio ζ ≥ 0
and velocities v, χ_i(ν, v) = −K_i (d + ζ v) exp(−½ dᵀK_i d), d = ν − η_i
(:func:`field_torques`).

:class:`FieldBasis` holds M shared fields (centres η: M×n, stiffnesses K: M×n×n),
:class:`MotionFields` each motion's own. Their time activations are
:mod:`tflearn.model.weights`, the two together :mod:`tflearn.model.program`.
"""
from __future__ import annotations

import math
from typing import Optional, Sequence

import torch
from torch import nn

__all__ = ["K_KINDS", "K_RANGE", "ETA_MAX", "as_float", "Stiffness", "FieldBasis", "field_torques",
           "MotionFields"]

K_KINDS = ("scalar", "diag", "block", "full")
K_RANGE = (1e-2, 20.0)      # bounds on the stiffness factors kept by FieldBasis.project_
ETA_MAX = 2 * math.pi       # bound on |η_k| kept by FieldBasis.project_


def as_float(x) -> torch.Tensor:
    """x as a float64 tensor (modules are built in float64; use ``.to()`` for others)."""
    return torch.as_tensor(x, dtype=torch.float64)


def _block_mask(blocks: Sequence[int], kind: str) -> torch.Tensor:
    n = sum(blocks)
    if kind == "full":
        return torch.ones(n, n, dtype=torch.bool).tril()
    if kind == "diag":
        return torch.eye(n, dtype=torch.bool)
    mask = torch.zeros(n, n, dtype=torch.bool)
    k = 0
    for b in blocks:
        mask[k:k + b, k:k + b] = True
        k += b
    return mask.tril()


class Stiffness(nn.Module):
    """M positive-definite stiffness matrices K (M×n×n).

    ``scalar``: K = exp(κ) I.  Others: K = L Lᵀ with L lower triangular on the kind's
    sparsity pattern and diag(L) = exp(diagonal parameters) > 0.
    """

    def __init__(self, K: torch.Tensor, kind: str = "diag",
                 blocks: Optional[Sequence[int]] = None):
        super().__init__()
        if kind not in K_KINDS:
            raise ValueError(f"unknown stiffness kind {kind!r} (expected one of {K_KINDS})")
        K = as_float(K)
        n = K.shape[-1]
        self.kind, self.n = kind, n
        blocks = list(blocks) if blocks is not None else [n]
        if sum(blocks) != n:
            raise ValueError(f"stiffness blocks {blocks} do not add up to {n}")
        if kind == "scalar":
            k = torch.diagonal(K, dim1=-2, dim2=-1).mean(-1)
            self.raw = nn.Parameter(torch.log(k))
            self.register_buffer("mask", torch.zeros(0, dtype=torch.bool))
        else:
            mask = _block_mask(blocks, kind)
            Kp = torch.where(mask | mask.T, K, torch.zeros_like(K))
            L = torch.linalg.cholesky(Kp)
            raw = torch.where(mask, L, torch.zeros_like(L))
            idx = torch.arange(n)
            raw[:, idx, idx] = torch.log(L[:, idx, idx])
            self.raw = nn.Parameter(raw)
            self.register_buffer("mask", mask)

    def factor(self, raw: Optional[torch.Tensor] = None) -> torch.Tensor:
        """L (M×n×n), lower triangular with positive diagonal (not for ``scalar``), of
        the stored parameters or of ``raw`` (...×n×n) laid out like them."""
        raw = self.raw if raw is None else raw
        eye = torch.eye(self.n, dtype=torch.bool, device=raw.device)
        off = torch.where(self.mask & ~eye, raw, torch.zeros_like(raw))
        return off + torch.diag_embed(torch.exp(torch.diagonal(raw, dim1=-2, dim2=-1)))

    @torch.no_grad()
    def project_(self, k_min: float = K_RANGE[0], k_max: float = K_RANGE[1]) -> None:
        """Keep k (scalar) or each diag(L)² in [k_min, k_max] and |L_ij| ≤ √k_max, so K stays
        bounded: λ_max(K) ≤ ‖L‖_F² ≤ n(n+1)/2 · k_max for a full factor (n(n+1)/2 entries of
        L, each squared ≤ k_max), k_max for scalar and diag, and the largest block's
        b(b+1)/2 · k_max for block. A stiffness no motion constrains cannot run off and
        make simulations stiff."""
        if self.kind == "scalar":
            self.raw.clamp_(math.log(k_min), math.log(k_max))
            return
        n = self.n
        idx = torch.arange(n)
        diag = self.raw[:, idx, idx].clamp(0.5 * math.log(k_min), 0.5 * math.log(k_max))
        self.raw.clamp_(-math.sqrt(k_max), math.sqrt(k_max))
        self.raw[:, idx, idx] = diag

    def forward(self, raw: Optional[torch.Tensor] = None) -> torch.Tensor:
        """K (M×n×n) of the stored parameters, or (...×n×n) of ``raw`` laid out like them
        (κ (...) for ``scalar``)."""
        raw = self.raw if raw is None else raw
        if self.kind == "scalar":
            eye = torch.eye(self.n, dtype=raw.dtype, device=raw.device)
            return torch.exp(raw)[..., None, None] * eye
        L = self.factor(raw)
        return L @ L.transpose(-1, -2)


class FieldBasis(nn.Module):
    """M shared torque fields over n coordinates: centres η (M×n), stiffnesses K and the
    damping ratio ζ (s, ≥ 0) of every field (D_i = ζ K_i; 0: no damping).

    ``forward(q, v)`` maps coordinates q and velocities v (...×n) to the field values χ
    (...×M×n); without v (or with ζ = 0) the fields are the thesis' χ_i(ν).
    """

    def __init__(self, eta: torch.Tensor, K: torch.Tensor, kind: str = "diag",
                 blocks: Optional[Sequence[int]] = None, damping: float = 0.0):
        super().__init__()
        if not (damping >= 0 and math.isfinite(damping)):
            raise ValueError(f"FieldBasis: the damping ratio must be finite and ≥ 0, got {damping}")
        self.damping = float(damping)
        eta = as_float(eta)
        K = as_float(K)
        if eta.ndim != 2 or K.shape != eta.shape + eta.shape[-1:]:
            raise ValueError(f"FieldBasis: eta must be M×n and K M×n×n, got "
                             f"{tuple(eta.shape)} and {tuple(K.shape)}")
        self.eta = nn.Parameter(eta.clone())
        self.blocks = list(blocks) if blocks is not None else [eta.shape[1]]
        self.stiffness = Stiffness(K, kind, self.blocks)

    @classmethod
    def empty(cls, n: int, kind: str = "diag", blocks: Optional[Sequence[int]] = None,
              damping: float = 0.0) -> FieldBasis:
        """A basis with no fields over n coordinates."""
        return cls(torch.zeros(0, n, dtype=torch.float64),
                   torch.zeros(0, n, n, dtype=torch.float64), kind=kind, blocks=blocks,
                   damping=damping)

    def like(self, eta: torch.Tensor, K: torch.Tensor) -> FieldBasis:
        """A new basis of fields η (k×n), K (k×n×n) of this basis' kind, blocks and
        damping ratio."""
        return FieldBasis(eta, K, kind=self.kind, blocks=self.blocks, damping=self.damping)

    @property
    def kind(self) -> str:
        return self.stiffness.kind

    @property
    def M(self) -> int:
        return self.eta.shape[0]

    @property
    def n(self) -> int:
        return self.eta.shape[1]

    def K(self) -> torch.Tensor:
        """Stiffness matrices (M×n×n)."""
        return self.stiffness()

    @property
    def free_stiffness(self) -> Optional[torch.Tensor]:
        """The flat indices (into n·n) of the stiffness parameters the kind leaves free —
        not the structural zeros of ``diag`` or ``block`` —, or None for ``scalar`` (one κ)."""
        return None if self.kind == "scalar" else self.stiffness.mask.reshape(-1).nonzero().squeeze(-1)

    @property
    def free_size(self) -> int:
        """p = n + s: a field's centre and its s free stiffness parameters."""
        free = self.free_stiffness
        return self.n + (1 if free is None else free.numel())

    @torch.no_grad()
    def free_vector(self) -> torch.Tensor:
        """θ (M×p): each field's centre η_i and free stiffness parameters (κ for scalar,
        else the free entries of L's parameters, log L_kk on the diagonal)."""
        free, raw = self.free_stiffness, self.stiffness.raw.detach().reshape(self.M, -1)
        raw = raw if free is None else raw[:, free]
        return torch.cat([self.eta.detach(), raw.reshape(self.M, self.free_size - self.n)], dim=-1)

    def split_free(self, theta: torch.Tensor) -> tuple:
        """θ (...×p) → (η (...×n), the stiffness parameters: κ (...) for scalar, else
        (...×n×n) laid out as :attr:`Stiffness.raw`); differentiable."""
        n, free = self.n, self.free_stiffness
        eta, rest = theta[..., :n], theta[..., n:]
        if free is None:
            return eta, rest[..., 0]
        raw = torch.zeros(theta.shape[:-1] + (n * n,), dtype=theta.dtype).index_copy(-1, free, rest)
        return eta, raw.reshape(theta.shape[:-1] + (n, n))

    @torch.no_grad()
    def assign_free(self, theta: torch.Tensor) -> None:
        """Set every field from θ (M×p, :meth:`free_vector`'s layout), then
        :meth:`project_`."""
        eta, raw = self.split_free(theta)
        self.eta.copy_(eta)
        self.stiffness.raw.copy_(raw)
        self.project_()

    @torch.no_grad()
    def select(self, idx: Sequence[int]) -> FieldBasis:
        """A new basis (detached) holding fields ``idx`` in that order."""
        idx = torch.as_tensor(list(idx), dtype=torch.long)
        return self.like(self.eta[idx], self.K()[idx])

    @torch.no_grad()
    def extend(self, eta: torch.Tensor, K: torch.Tensor) -> FieldBasis:
        """A new basis (detached): these fields followed by new ones, η (k×n), K (k×n×n)."""
        return self.like(torch.cat([self.eta, as_float(eta)]), torch.cat([self.K(), as_float(K)]))

    @torch.no_grad()
    def project_(self) -> None:
        """Keep |η_k| ≤ ETA_MAX and the stiffness within K_RANGE (see Stiffness.project_)."""
        self.eta.clamp_(-ETA_MAX, ETA_MAX)
        self.stiffness.project_()

    @torch.no_grad()
    def gaussians(self, q: torch.Tensor) -> torch.Tensor:
        """g_i(q) = exp(−½ dᵀK_i d), d = q − η_i, of every field: q (...×n) → (...×M), the
        factor by which field i's torque falls off away from its centre."""
        d = q.unsqueeze(-2) - self.eta
        return torch.exp(-0.5 * torch.einsum("...mi,mij,...mj->...m", d, self.K(), d))

    def forward(self, q: torch.Tensor, v: Optional[torch.Tensor] = None) -> torch.Tensor:
        """χ_i(q, v) for every field (:func:`field_torques`): q, v (...×n) → (...×M×n).
        Scalar and diagonal stiffness take the product K d elementwise."""
        K = self.K()
        if self.kind in ("scalar", "diag"):
            return field_torques(q, v, self.eta, torch.diagonal(K, dim1=-2, dim2=-1), self.damping,
                                 diagonal=True)
        return field_torques(q, v, self.eta, K, self.damping)

    @torch.no_grad()
    def tables(self) -> tuple:
        """(η (1×M×n), K (1×M×n×n), ζ, per motion = False): the fields as one group,
        shared by every motion (for :meth:`tflearn.model.program.FieldProgram.rows`)."""
        return self.eta.detach()[None], self.K()[None], self.damping, False


def field_torques(q: torch.Tensor, v: Optional[torch.Tensor], eta: torch.Tensor, K: torch.Tensor,
                  damping: float = 0.0, diagonal: bool = False) -> torch.Tensor:
    """χ_i(q, v) = −K_i (d + ζ v) exp(−½ dᵀK_i d), d = q − η_i, for fields η (...×M×n) and
    K (...×M×n×n; with ``diagonal``, K's diagonal ...×M×n) that broadcast against q, v
    (...×n) → (...×M×n). Without v, or with ζ = 0, χ_i(q) = −K_i d exp(−½ dᵀK_i d)."""
    def times_K(x):
        return K * x if diagonal else torch.einsum("...ij,...j->...i", K, x)   # one batched product
    d = q.unsqueeze(-2) - eta
    Kd = times_K(d)
    g = torch.exp(-0.5 * (d * Kd).sum(-1, keepdim=True))
    if damping and v is not None:
        return -(Kd + damping * times_K(v.unsqueeze(-2))) * g
    return -Kd * g


class MotionFields(nn.Module):
    """Each motion's own fields, η (N×m×n) and K (N×m×n×n), with damping ratio ζ, as a
    basis for :class:`~tflearn.model.program.FieldProgram`: χ(q, v) for q, v (...×N×n) →
    (...×N×m×n), motion j's fields only."""

    def __init__(self, eta: torch.Tensor, K: torch.Tensor, damping: float = 0.0):
        super().__init__()
        self.eta, self.K, self.damping = eta, K, float(damping)

    def forward(self, q, v=None):
        return field_torques(q, v, self.eta, self.K, self.damping)

    def tables(self) -> tuple:
        """(η, K, ζ, per motion): one group of fields per motion (for
        :meth:`tflearn.model.program.FieldProgram.rows`)."""
        return self.eta.detach(), self.K.detach(), self.damping, True
