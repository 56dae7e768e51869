"""Compiled (numba) loops of the simulator's state, for evaluations that need no gradient:
:func:`tflearn.physics.configspace.unpack` and ``position_rate`` hand the state to
:func:`read_state` and :func:`position_rate` when :func:`tflearn.physics.kernels.applies`
(float64 CPU tensors, no gradient), and the compiled simulator
(:mod:`tflearn.simulation.simkernel`) calls them on every stage.

Compiled with the flags of :mod:`tflearn.physics.kernels` (``kernels._FAST``) and cached
in its folder (:func:`tflearn.physics.kernels.cache_folder`, whose digest covers this file).
"""
from __future__ import annotations

import numba
import numpy as np
from numba import njit

from . import kernels

_NUMBA_CACHE_DIR = kernels.redirect_cache()          # restored at the end of this module


@njit(cache=True, fastmath=kernels._FAST)
def read_state(y, quat, other, coords_order, coords, quats, R):
    """:func:`tflearn.physics.configspace.unpack` for every sample b of the state y (B×D): each
    rotation joint's quaternion (entries ``quat``, nr×4 indices into y) normalised into
    ``quats`` (B×nr×4), its rotation matrix into R (B×nr×3×3) and its principal rotation
    vector, with the other position entries (``other``), put in coordinate order
    (``coords_order``) into ``coords`` (B×nv) — the formulas of
    :func:`tflearn.physics.configspace.quat_to_rotvec` and
    :func:`~tflearn.physics.configspace.quat_to_rotmat`."""
    B, nr = y.shape[0], quat.shape[0]
    flat = np.empty(3 * nr + other.shape[0])
    for b in range(B):
        for j in range(nr):
            x, yy, z, w = y[b, quat[j, 0]], y[b, quat[j, 1]], y[b, quat[j, 2]], y[b, quat[j, 3]]
            n = np.sqrt(x * x + yy * yy + z * z + w * w)
            x, yy, z, w = x / n, yy / n, z / n, w / n
            quats[b, j, 0], quats[b, j, 1], quats[b, j, 2], quats[b, j, 3] = x, yy, z, w
            (R[b, j, 0, 0], R[b, j, 0, 1], R[b, j, 0, 2], R[b, j, 1, 0], R[b, j, 1, 1], R[b, j, 1, 2],
             R[b, j, 2, 0], R[b, j, 2, 1], R[b, j, 2, 2]) = kernels._quat_rotmat(x, yy, z, w)
            if not w > 0:                                  # the shortest arc: w > 0
                x, yy, z, w = -x, -yy, -z, -w
            u = np.sqrt(x * x + yy * yy + z * z)
            if u < 1e-3 * w:                               # atan(r)/r by its series
                r2 = (u / w) ** 2
                f = (2 / w) * (1 - r2 / 3 + r2 * r2 / 5 - r2 ** 3 / 7)
            else:
                f = 2 * np.arctan2(u, w) / u
            flat[3 * j], flat[3 * j + 1], flat[3 * j + 2] = f * x, f * yy, f * z
        for k in range(other.shape[0]):
            flat[3 * nr + k] = y[b, other[k]]
        for k in range(coords_order.shape[0]):
            coords[b, k] = flat[coords_order[k]]


@njit(cache=True, fastmath=kernels._FAST)
def position_rate(kind, rot, offset, R, quats, v, position_order, out):
    """:func:`tflearn.physics.configspace.position_rate` for every sample b: q̇ = ½ q ⊗ (ω, 0) per
    rotation joint (ω its first three velocities), θ̇ = v per hinge, ṫ = R u per free
    joint (u its last three), put in the state's order (``position_order``) into ``out``
    (B×n_position); the per-link tables of :func:`tflearn.physics.kernels.aba`."""
    B, nr, L = v.shape[0], quats.shape[1], kind.shape[0]
    flat = np.empty(position_order.shape[0])
    for b in range(B):
        k = 4 * nr
        for i in range(L):
            o = offset[i]
            if kind[i] >= 2:
                j = rot[i]
                x, yy, z, w = quats[b, j, 0], quats[b, j, 1], quats[b, j, 2], quats[b, j, 3]
                w0, w1, w2 = v[b, o], v[b, o + 1], v[b, o + 2]
                flat[4 * j] = 0.5 * (w * w0 + yy * w2 - z * w1)
                flat[4 * j + 1] = 0.5 * (w * w1 + z * w0 - x * w2)
                flat[4 * j + 2] = 0.5 * (w * w2 + x * w1 - yy * w0)
                flat[4 * j + 3] = -0.5 * (x * w0 + yy * w1 + z * w2)
                if kind[i] == 3:
                    for m in range(3):
                        flat[k + m] = (R[b, j, m, 0] * v[b, o + 3] + R[b, j, m, 1] * v[b, o + 4]
                                       + R[b, j, m, 2] * v[b, o + 5])
                    k += 3
            elif kind[i] == 1:
                flat[k] = v[b, o]
                k += 1
        for m in range(position_order.shape[0]):
            out[b, m] = flat[position_order[m]]


numba.config.CACHE_DIR = _NUMBA_CACHE_DIR
