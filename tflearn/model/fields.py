"""Torque fields (thesis §3.2–3.3): shared basis fields, time profiles, per-motion weights.

A field i is the gradient of a Gaussian over coordinates ν (n = nv):

    χ_i(ν) = −K_i (ν − η_i) · exp(−½ (ν − η_i)ᵀ K_i (ν − η_i))

with K_i positive definite by construction in one of four kinds: ``scalar`` (k·I),
``diag``, ``block`` (one full block per joint, e.g. 3×3, 1×1, 3×3 for the arm) or ``full``
(K = L Lᵀ with L lower triangular and a positive diagonal).

Motion j is driven by
    τ_j(t) = Σ_i (a_ji ψ((t − s_ji)/d_ji) + b_ji φ((t − p_ji)/e_ji)) χ_i(ν(t))
with the smooth step ψ(u) = u − sin(2πu)/2π on [0, 1] (0 before, 1 after) and the cosine
pulse φ(u) = ½(1 − cos 2πu) on [0, 1] (0 elsewhere); a, b ≥ 0. Onsets s, p default to 0
and durations d, e to the motion's duration λ (the thesis' fixed phase).

Activation sequences (thesis §4.5.2 "variable phase", generalised): a motion may also
have P sub-movement windows k with onsets o_jk and durations l_jk (shared by its
fields), and each field a pulse weight c_jik ≥ 0 on each window,

    w_ji(t) = a_ji ψ(·) + b_ji φ(·) + Σ_k c_jik φ((t − o_jk)/l_jk),

so a field can be switched on, off and on again within one motion; the activation
stays non-negative and C¹, and is still linear in the weights. P = 0 is the thesis'
model.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import torch
from torch import nn

K_KINDS = ("scalar", "diag", "block", "full")
K_RANGE = (1e-2, 20.0)      # bounds on the stiffness factors kept by FieldBasis.project_
ETA_MAX = 2 * math.pi       # bound on |η_k| kept by FieldBasis.project_


def as_float(x) -> torch.Tensor:
    """x as a float64 tensor (modules are built in float64; use ``.to()`` for others)."""
    return torch.as_tensor(x, dtype=torch.float64)


def step_profile(u: torch.Tensor) -> torch.Tensor:
    """ψ(u) = u − sin(2πu)/(2π) on [0, 1], 0 for u < 0, 1 for u > 1 (C¹ everywhere)."""
    u = u.clamp(0.0, 1.0)
    return u - torch.sin(2 * math.pi * u) / (2 * math.pi)


def pulse_profile(u: torch.Tensor) -> torch.Tensor:
    """φ(u) = ½(1 − cos 2πu) on [0, 1], 0 elsewhere (C¹ everywhere)."""
    u = u.clamp(0.0, 1.0)
    return 0.5 * (1 - torch.cos(2 * math.pi * u))


def step_slope(u: torch.Tensor) -> torch.Tensor:
    """ψ'(u) = 1 − cos 2πu on [0, 1], 0 elsewhere."""
    inside = (u >= 0) & (u <= 1)
    return torch.where(inside, 1 - torch.cos(2 * math.pi * u), torch.zeros_like(u))


def pulse_slope(u: torch.Tensor) -> torch.Tensor:
    """φ'(u) = π sin 2πu on [0, 1], 0 elsewhere."""
    inside = (u >= 0) & (u <= 1)
    return torch.where(inside, math.pi * torch.sin(2 * math.pi * u), torch.zeros_like(u))


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
        shared by every motion (for :meth:`FieldProgram.rows`)."""
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
    basis for :class:`FieldProgram`: χ(q, v) for q, v (...×N×n) → (...×N×m×n), motion
    j's fields only."""

    def __init__(self, eta: torch.Tensor, K: torch.Tensor, damping: float = 0.0):
        super().__init__()
        self.eta, self.K, self.damping = eta, K, float(damping)

    def forward(self, q, v=None):
        return field_torques(q, v, self.eta, self.K, self.damping)

    def tables(self) -> tuple:
        """(η, K, ζ, per motion): one group of fields per motion (for
        :meth:`FieldProgram.rows`)."""
        return self.eta.detach(), self.K.detach(), self.damping, True


class MotionWeights(nn.Module):
    """Per-motion weights for N motions, M fields and P sub-movement windows.

    Holds step weights a and pulse weights b (N×M) and window weights c (N×M×P), all
    non-negative (the module reads them through a clamp at zero and :meth:`project_`
    keeps the stored values there), step onsets/durations and pulse onsets/durations
    (N×M), window onsets/durations (N×P) and motion durations λ (N).
    """

    def __init__(self, a: torch.Tensor, b: torch.Tensor, duration: torch.Tensor,
                 step_onset=None, step_duration=None, pulse_onset=None, pulse_duration=None,
                 names: Optional[Sequence[str]] = None, c=None, window_onset=None,
                 window_duration=None):
        super().__init__()
        a = as_float(a)
        b = as_float(b)
        duration = as_float(duration).reshape(-1)
        if a.ndim != 2 or b.shape != a.shape or duration.shape[0] != a.shape[0]:
            raise ValueError("MotionWeights: a and b must be N×M and duration N")
        lam = duration[:, None].expand_as(a)

        def init(x, default):
            return (as_float(x) if x is not None else default).clone()
        windows = init(window_onset, torch.zeros(a.shape[0], 0, dtype=a.dtype))
        P = windows.shape[-1]
        if windows.shape != (a.shape[0], P) or (c is not None and as_float(c).shape != a.shape + (P,)):
            raise ValueError("MotionWeights: window onsets must be N×P and c N×M×P")
        self.a_raw = nn.Parameter(a.clone())
        self.b_raw = nn.Parameter(b.clone())
        self.c_raw = nn.Parameter(init(c, torch.zeros(a.shape + (P,), dtype=a.dtype)))
        self.window_onset = nn.Parameter(windows)
        self.window_duration = nn.Parameter(init(window_duration, duration[:, None].expand(-1, P)))
        self.step_onset = nn.Parameter(init(step_onset, torch.zeros_like(a)))
        self.step_duration = nn.Parameter(init(step_duration, lam))
        self.pulse_onset = nn.Parameter(init(pulse_onset, torch.zeros_like(a)))
        self.pulse_duration = nn.Parameter(init(pulse_duration, lam))
        self.register_buffer("duration", duration.clone())
        self.names = list(names) if names is not None else [f"motion{j}" for j in range(len(duration))]
        self.project_()

    TIMING = ("step_onset", "step_duration", "pulse_onset", "pulse_duration")
    PER_FIELD = ("a_raw", "b_raw", "c_raw", *TIMING)
    WINDOWS = ("window_onset", "window_duration")

    @classmethod
    def zeros(cls, M: int, duration: torch.Tensor, names: Optional[Sequence[str]] = None,
              windows: Optional[tuple] = None) -> MotionWeights:
        """Zero weights on M fields for motions of these durations (N), default phases;
        ``windows``: (onsets, durations) of P sub-movement windows (N×P each), none by
        default."""
        z = torch.zeros(len(duration), M, dtype=torch.float64)
        onset, length = windows if windows is not None else (None, None)
        return cls(z, z, duration, names=names, window_onset=onset, window_duration=length)

    @property
    def P(self) -> int:
        """The number of sub-movement windows per motion."""
        return self.window_onset.shape[-1]

    def _arrays(self) -> dict:
        return {k: getattr(self, k).detach() for k in self.PER_FIELD + self.WINDOWS}

    def _with(self, arrays: dict, duration=None, names=None) -> MotionWeights:
        a = arrays
        return MotionWeights(a["a_raw"], a["b_raw"], self.duration if duration is None else duration,
                             a["step_onset"], a["step_duration"], a["pulse_onset"],
                             a["pulse_duration"], names=self.names if names is None else names,
                             c=a["c_raw"], window_onset=a["window_onset"],
                             window_duration=a["window_duration"])

    def select_fields(self, idx: Sequence[int]) -> MotionWeights:
        """New weights (detached) on fields ``idx`` only, in that order."""
        idx = torch.as_tensor(list(idx), dtype=torch.long)
        return self._with({k: v[:, idx] if k in self.PER_FIELD else v
                           for k, v in self._arrays().items()})

    def take_fields(self, cols: torch.Tensor, pad: torch.Tensor) -> MotionWeights:
        """New weights (detached), motion j's on its own fields ``cols[j]`` (N×W indices),
        a, b and c 0 where ``pad`` (N×W bools)."""
        def take(k, x):                              # N×M(×P) → N×W(×P)
            idx = cols.reshape(cols.shape + (1,) * (x.ndim - 2)).expand(cols.shape + x.shape[2:])
            x = torch.gather(x, 1, idx)
            zero = k in ("a_raw", "b_raw", "c_raw")
            return x.masked_fill(pad.reshape(pad.shape + (1,) * (x.ndim - 2)), 0.0) if zero else x
        return self._with({k: take(k, v) if k in self.PER_FIELD else v for k, v in self._arrays().items()})

    def extend_fields(self, k: int = 1) -> MotionWeights:
        """New weights (detached) with k more fields: zero weights, default phases."""
        z = torch.zeros(self.N, k, dtype=self.a_raw.dtype)
        lam = self.duration[:, None].expand(self.N, k)
        fill = {"step_duration": lam, "pulse_duration": lam,
                "c_raw": torch.zeros(self.N, k, self.P, dtype=z.dtype)}
        return self._with({key: torch.cat([v, fill.get(key, z)], dim=1) if key in self.PER_FIELD else v
                           for key, v in self._arrays().items()})

    def select_motions(self, idx: Sequence[int]) -> MotionWeights:
        """New weights (detached) of motions ``idx`` only, in that order."""
        idx = torch.as_tensor(list(idx), dtype=torch.long)
        return self._with({k: v[idx] for k, v in self._arrays().items()},
                          duration=self.duration[idx], names=[self.names[i] for i in idx.tolist()])

    def timing(self, j: int, weights: bool = False) -> dict:
        """Motion j's activation timing (detached copies): {name: (M,)} over :attr:`TIMING`
        and {name: (P,)} over :attr:`WINDOWS`; with ``weights`` its weights too (a_raw,
        b_raw: (M,); c_raw: (M×P))."""
        keys = self.TIMING + self.WINDOWS + (("a_raw", "b_raw", "c_raw") if weights else ())
        return {k: getattr(self, k).detach()[j].clone() for k in keys}

    @property
    def a(self) -> torch.Tensor:
        return self.a_raw.clamp(min=0.0)

    @property
    def b(self) -> torch.Tensor:
        return self.b_raw.clamp(min=0.0)

    @property
    def c(self) -> torch.Tensor:
        return self.c_raw.clamp(min=0.0)

    def used(self) -> torch.Tensor:
        """N×M bools: whether motion j has a weight (a, b or c > 0) on field i."""
        with torch.no_grad():
            return (self.a + self.b + self.c.sum(-1)) > 0

    def vector(self) -> torch.Tensor:
        """x = [a (M) | b (M) | c (M·P, field by field)] per motion (N×M(2+P)): the layout
        of :func:`tflearn.fit.torque.design`'s columns."""
        return torch.cat([self.a, self.b, self.c.reshape(self.N, -1)], dim=-1)

    @torch.no_grad()
    def set_vector(self, x: torch.Tensor) -> None:
        """Store x (N×M(2+P), the layout of :meth:`vector`) as a, b, c."""
        M = self.a_raw.shape[1]
        self.a_raw.copy_(x[:, :M])
        self.b_raw.copy_(x[:, M:2 * M])
        self.c_raw.copy_(x[:, 2 * M:].reshape(self.c_raw.shape))

    @property
    def N(self) -> int:
        return self.a_raw.shape[0]

    def phase_parameters(self) -> list:
        return [self.step_onset, self.step_duration, self.pulse_onset, self.pulse_duration,
                self.window_onset, self.window_duration]

    @torch.no_grad()
    def project_(self, min_duration: float = 1e-2) -> None:
        """Project onto the feasible set: a, b, c ≥ 0, durations ≥ ``min_duration``."""
        for w in (self.a_raw, self.b_raw, self.c_raw):
            w.clamp_(min=0.0)
        for d in (self.step_duration, self.pulse_duration, self.window_duration):
            d.clamp_(min=min_duration)

    def profiles(self, t: torch.Tensor):
        """ψ_ji(t), φ_ji(t): (N×M) each for a scalar t, or (T×N×M) for t (T)."""
        return self.profiles_at(torch.as_tensor(t, dtype=self.a_raw.dtype)[..., None])

    def profiles_at(self, t: torch.Tensor):
        """ψ, φ at each motion's own time: t (...×N) → (...×N×M) each."""
        tt = t[..., None]
        return (step_profile((tt - self.step_onset) / self.step_duration),
                pulse_profile((tt - self.pulse_onset) / self.pulse_duration))

    def profiles_per_motion(self, t: torch.Tensor):
        """ψ, φ at each motion's own times: t (N×T) → (N×T×M) each."""
        return tuple(x.transpose(0, 1) for x in self.profiles_at(t.transpose(0, 1)))

    def windows(self, t: torch.Tensor) -> torch.Tensor:
        """The window pulses φ((t − o_jk)/l_jk): (N×P) for a scalar t, (T×N×P) for t (T)."""
        return self.windows_at(torch.as_tensor(t, dtype=self.a_raw.dtype)[..., None])

    def windows_at(self, t: torch.Tensor) -> torch.Tensor:
        """The window pulses at each motion's own time: t (...×N) → (...×N×P)."""
        return pulse_profile((t[..., None] - self.window_onset) / self.window_duration)

    def windows_per_motion(self, t: torch.Tensor) -> torch.Tensor:
        """The window pulses at each motion's own times: t (N×T) → (N×T×P)."""
        return self.windows_at(t.transpose(0, 1)).transpose(0, 1)

    def activation(self, t: torch.Tensor) -> torch.Tensor:
        """w_ji(t) = a_ji ψ_ji(t) + b_ji φ_ji(t) + Σ_k c_jik φ_jk(t): (N×M), or (T×N×M) for
        t (T)."""
        return self.activation_at(torch.as_tensor(t, dtype=self.a_raw.dtype)[..., None])

    def activation_at(self, t: torch.Tensor) -> torch.Tensor:
        """The activations w_ji at each motion's own time: t (...×N) → (...×N×M)."""
        psi, phi = self.profiles_at(t)
        w = self.a * psi + self.b * phi
        if self.P:
            w = w + (self.c * self.windows_at(t).unsqueeze(-2)).sum(-1)
        return w

    def flat(self, keys: Sequence[str]) -> torch.Tensor:
        """The arrays ``keys`` (of :attr:`PER_FIELD` and :attr:`WINDOWS`) of each motion,
        detached, flattened and concatenated: (N×D)."""
        return torch.cat([getattr(self, k).detach().reshape(self.N, -1) for k in keys], dim=-1)

    @torch.no_grad()
    def set_flat(self, keys: Sequence[str], x: torch.Tensor, motions: Sequence[int]) -> None:
        """Store x (len(motions)×D, the layout of :meth:`flat`) as the arrays ``keys`` of
        motions ``motions``, in place."""
        idx, k = torch.as_tensor(list(motions), dtype=torch.long), 0
        for key in keys:
            p = getattr(self, key)
            d = math.prod(p.shape[1:])
            p[idx] = x[:, k:k + d].reshape((len(idx),) + p.shape[1:]).to(p.dtype)
            k += d

    def with_flat(self, keys: Sequence[str], x: torch.Tensor, motions: Sequence[int]) -> MotionWeights:
        """New weights (detached) with one row r per entry of ``motions``: motion
        motions[r]'s, its arrays ``keys`` replaced by x[r] (the layout of :meth:`flat`;
        x: len(motions)×D)."""
        out = self.select_motions(motions)
        arrays, k = out._arrays(), 0
        for key in keys:
            shape = arrays[key].shape
            d = math.prod(shape[1:])
            arrays[key] = x[:, k:k + d].reshape(shape)
            k += d
        return out._with(arrays)


class FieldProgram(nn.Module):
    """The torque program of N motions: τ(t, ν, v) = Σ_i w_ji(t) χ_i(ν, v) for each motion j.

    Called as ``program(t, q, v)`` with q, v (...×N×n) — the motion index on the last batch
    dimension — it returns τ (...×N×n). ``index`` restricts it to some motions. ``start``
    (N): each motion's own time at the simulation's t = 0, its program then run at
    start + t (the segments of multiple shooting). t is a scalar, sample times (T, with q
    T×N×n), or a time per member (of q's batch shape, ...×N: the per-member steps of
    :class:`~tflearn.simulation.simulate.SimOptions` batch ``each``).
    """

    def __init__(self, basis: FieldBasis, weights: MotionWeights,
                 index: Optional[Sequence[int]] = None, start: Optional[torch.Tensor] = None):
        super().__init__()
        self.basis, self.weights, self.start = basis, weights, start
        self.index = None if index is None else torch.as_tensor(index, dtype=torch.long)

    def forward(self, t, q, v=None):
        t = torch.as_tensor(t, dtype=q.dtype)
        each = t.ndim > 0 and t.shape == q.shape[:-1]  # a time per member
        if each and self.index is not None:          # ... of the indexed motions
            t = t.new_zeros(t.shape[:-1] + (self.weights.N,)).index_copy(-1, self.index, t)
        if self.start is not None:
            t = self.start + (t if each else t[..., None])
            each = True
        w = self.weights.activation_at(t if each else t[..., None])
        if self.index is not None:
            w = w[..., self.index, :]
        chi = self.basis(q, v)
        return (w.unsqueeze(-1) * chi).sum(-2)

    @torch.no_grad()
    def rows(self, batch: torch.Size) -> Optional[ProgramRows]:
        """The program of every member of a batch of this shape (...×N', N' the motions it
        is called with), row by row in the flattened batch's order, for the compiled
        simulator (:mod:`tflearn.simulation.simkernel`); None when the basis cannot say what its
        fields are (it has no ``tables``)."""
        if not hasattr(self.basis, "tables"):
            return None
        W = self.weights
        motion = torch.arange(W.N) if self.index is None else self.index
        if not batch or batch[-1] != len(motion):
            return None
        motion = motion.repeat(math.prod(batch[:-1]))
        eta, K, zeta, per_motion = self.basis.tables()
        pick = lambda x: x.detach()[motion]
        start = torch.zeros(len(motion), dtype=torch.float64) if self.start is None else pick(self.start)
        return ProgramRows(
            group=motion if per_motion else torch.zeros_like(motion), start=start,
            a=pick(W.a), b=pick(W.b), c=pick(W.c),
            **{k: pick(getattr(W, k)) for k in W.TIMING + W.WINDOWS},
            eta=eta, K=K, damping=torch.full((eta.shape[0],), float(zeta), dtype=torch.float64))


@dataclass
class ProgramRows:
    """A field program unrolled per member b of a flattened batch (B rows), for the
    compiled simulator: member b runs motion time start_b + t and is driven by

        τ_b = Σ_i w_bi χ_gi(ν, v),  g = group_b,
        w_bi = a_bi ψ((t' − so_bi)/sd_bi) + b_bi φ((t' − po_bi)/pd_bi) + Σ_k c_bik φ((t' − wo_bk)/wd_bk)

    with the fields of group g: η (G×M×n), K (G×M×n×n), ζ (G). Per row: group, start
    (B); a, b and the step/pulse onsets and durations (B×M); c (B×M×P); window onsets
    and durations (B×P). :func:`stack_rows` joins several programs' rows."""

    group: torch.Tensor
    start: torch.Tensor
    a: torch.Tensor
    b: torch.Tensor
    c: torch.Tensor
    step_onset: torch.Tensor
    step_duration: torch.Tensor
    pulse_onset: torch.Tensor
    pulse_duration: torch.Tensor
    window_onset: torch.Tensor
    window_duration: torch.Tensor
    eta: torch.Tensor
    K: torch.Tensor
    damping: torch.Tensor


def stack_rows(parts: Sequence[ProgramRows]) -> ProgramRows:
    """Several programs' rows one after another (their field groups kept apart), padded to
    the largest M and P with fields and windows of zero weight (durations 1)."""
    M = max(p.a.shape[1] for p in parts)
    P = max(p.c.shape[2] for p in parts)

    def pad(x, dims, value=0.0):                       # dims: [(dimension, new size)]
        size = dict(dims)
        widths = []
        for d in range(x.ndim - 1, min(size) - 1, -1):
            widths += [0, size.get(d, x.shape[d]) - x.shape[d]]
        return nn.functional.pad(x, widths, value=value)
    out, groups = {}, 0
    for p in parts:
        item = {"group": p.group + groups, "start": p.start, "damping": p.damping,
                "a": pad(p.a, [(1, M)]), "b": pad(p.b, [(1, M)]), "c": pad(p.c, [(1, M), (2, P)]),
                "step_onset": pad(p.step_onset, [(1, M)]), "pulse_onset": pad(p.pulse_onset, [(1, M)]),
                "step_duration": pad(p.step_duration, [(1, M)], 1.0),
                "pulse_duration": pad(p.pulse_duration, [(1, M)], 1.0),
                "window_onset": pad(p.window_onset, [(1, P)]),
                "window_duration": pad(p.window_duration, [(1, P)], 1.0),
                "eta": pad(p.eta, [(1, M)]), "K": pad(p.K, [(1, M)])}
        groups += p.eta.shape[0]
        for k, x in item.items():
            out.setdefault(k, []).append(x)
    return ProgramRows(**{k: torch.cat(x) for k, x in out.items()})


# ------------------------------------------------------------------ the model's one state

def model_state(basis: FieldBasis, weights: MotionWeights) -> dict:
    """The exact state of a model (basis + weights) as plain tensors and JSON values: the
    one serialisation used by checkpoints, path matching's best point and experiment rows
    (:func:`state_to_json` for JSON files). :func:`model_from_state` inverts it exactly."""
    return {"basis": {k: v.detach().clone() for k, v in basis.state_dict().items()},
            "weights": {k: v.detach().clone() for k, v in weights.state_dict().items()},
            "kind": basis.kind, "blocks": list(basis.blocks), "damping": basis.damping,
            "names": list(weights.names)}


def model_from_state(state: dict) -> tuple:
    """(FieldBasis, MotionWeights) from :func:`model_state` (tensors or nested lists; a
    state written before field damping and windows existed has ζ = 0 and P = 0)."""
    def tensors(d):
        return {k: v if isinstance(v, torch.Tensor) else torch.tensor(v, dtype=torch.float64)
                for k, v in d.items()}
    b, w = tensors(state["basis"]), tensors(state["weights"])
    M, n = b["eta"].shape
    basis = FieldBasis(torch.zeros(M, n, dtype=torch.float64),
                       torch.eye(n, dtype=torch.float64).expand(M, n, n),
                       kind=state["kind"], blocks=state["blocks"],
                       damping=state.get("damping", 0.0))
    basis.load_state_dict(b)
    N = w["duration"].shape[0]
    none = torch.zeros(N, 0, dtype=torch.float64)       # a state from before windows: P = 0
    w.setdefault("window_onset", none)
    w.setdefault("window_duration", none)
    w.setdefault("c_raw", torch.zeros(N, M, 0, dtype=torch.float64))
    weights = MotionWeights.zeros(M, w["duration"], names=state["names"],
                                  windows=(w["window_onset"], w["window_duration"]))
    weights.load_state_dict(w)
    return basis, weights


def state_to_json(state: dict) -> dict:
    """A :func:`model_state` with every tensor as a nested list (float64 values are kept
    exactly by JSON's shortest round-trip repr)."""
    return {k: ({n: v.tolist() for n, v in x.items()} if k in ("basis", "weights") else x)
            for k, x in state.items()}
