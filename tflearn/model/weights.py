"""Per-motion weights and time profiles (thesis §3.3): when and how strongly each field acts.

Motion j is driven by
    τ_j(t) = Σ_i (a_ji ψ((t − s_ji)/d_ji) + b_ji φ((t − p_ji)/e_ji)) χ_i(ν(t))
with the fields χ_i of :mod:`tflearn.model.fields`, the smooth step
ψ(u) = u − sin(2πu)/2π on [0, 1] (0 before, 1 after) and the cosine pulse
φ(u) = ½(1 − cos 2πu) on [0, 1] (0 elsewhere); a, b ≥ 0. Onsets s, p default to 0 and
durations d, e to the motion's duration λ (the thesis' fixed phase).

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
from typing import Optional, Sequence

import torch
from torch import nn

from .fields import as_float

__all__ = ["step_profile", "pulse_profile", "step_slope", "pulse_slope", "MotionWeights"]


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

    def with_windows(self, onset: torch.Tensor, duration: torch.Tensor) -> MotionWeights:
        """New weights (detached) with these sub-movement windows (onsets, durations: N×P)
        in place of the motions' own, every window weight c zero."""
        arrays = self._arrays()
        arrays.update(window_onset=as_float(onset), window_duration=as_float(duration),
                      c_raw=torch.zeros(arrays["a_raw"].shape + (onset.shape[-1],), dtype=torch.float64))
        return self._with(arrays)

    def select_motions(self, idx: Sequence[int]) -> MotionWeights:
        """New weights (detached) of motions ``idx`` only, in that order."""
        idx = torch.as_tensor(list(idx), dtype=torch.long)
        return self._with({k: v[idx] for k, v in self._arrays().items()},
                          duration=self.duration[idx], names=[self.names[i] for i in idx.tolist()])

    @staticmethod
    def concat(parts: Sequence[MotionWeights]) -> MotionWeights:
        """New weights (detached) of the motions of ``parts`` in turn (the same M and P)."""
        arrays = [p._arrays() for p in parts]
        return parts[0]._with({k: torch.cat([a[k] for a in arrays]) for k in arrays[0]},
                              duration=torch.cat([p.duration for p in parts]),
                              names=[n for p in parts for n in p.names])

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
    def permute_windows_(self, order: torch.Tensor) -> None:
        """Reorder every motion's windows in place: its window k becomes its window
        order[j, k] (N×P; onsets, durations and the weights c together)."""
        for key in self.WINDOWS:
            getattr(self, key).copy_(getattr(self, key).gather(1, order))
        self.c_raw.copy_(self.c_raw.gather(2, order[:, None, :].expand_as(self.c_raw)))

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

    @torch.no_grad()
    def put_(self, j: int, fields: Sequence[int], arrays: dict) -> None:
        """Motion j on ``fields`` (positions) alone, in place: its a, b, c zero elsewhere,
        ``arrays`` (:meth:`timing` with weights: per field, or per motion for the
        windows) written into those fields' columns."""
        for key in ("a_raw", "b_raw", "c_raw"):
            getattr(self, key)[j] = 0.0
        for key, row in arrays.items():
            if key in self.WINDOWS:
                getattr(self, key)[j] = row
            else:
                getattr(self, key)[j, list(fields)] = row

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
