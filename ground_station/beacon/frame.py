"""The formation-cylindrical frame and its transforms.

B = c + s a + rho (cos phi e1 + sin phi e2), y = [s, rho, phi, v_s, v_rho, v_phi] (the velocity
in the local basis (a, e_rho, e_phi) at B): c the centroid of the present UAVs' estimates, a
their principal axis, e1 the unit normal from the axis towards the predicted beacon, e2 = a x e1
(why: ground_station.beacon).  Rows whose track is in plain ECEF carry ``cart`` True and pass
through unchanged.  ut_to_ecef gives the published ECEF moments (the unscented transform)."""
from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

__all__ = ["Frame", "formation_frame", "cyl_to_ecef", "ecef_to_cyl", "ut_to_ecef"]

_UT_C2 = 6.0  # n + lambda of the sigma points (alpha = 1, kappa = 0): +-sqrt(6) sigma, W0 = 0


class Frame(NamedTuple):
    """Formation-cylindrical frames, one per row: origin c, axis a, normals e1, e2 (T, 3);
    cart (T,) True where the row's state is plain ECEF instead (see formation_frame)."""

    c: np.ndarray
    a: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    cart: np.ndarray

    def take(self, idx) -> "Frame":
        return Frame(*(v[idx] for v in self))


# The geometry below runs every epoch on small arrays, where numpy's per-call overhead is
# the cost: reductions call np.add.reduce directly (what np.sum calls) and results are
# written into preallocated arrays instead of np.stack -- the same operations on the same
# numbers, so the same results bit for bit.
_sum = np.add.reduce


def _unit(v):
    return v / np.sqrt(_sum(v * v, axis=-1, keepdims=True))


def _cross(a, b):
    out = np.empty(np.broadcast_shapes(np.shape(a), np.shape(b)))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def formation_frame(upos, mask, beacon_pos, prev: Frame | None = None, axis_ratio: float = 0.5) -> Frame:
    """The frame of each row: centroid and principal axis of the present UAVs (previous
    frame's where fewer than 2 are present, previous axis where the formation is not
    line-like), e1 towards ``beacon_pos`` (so that phi = 0 there).

    Which rows use the cylindrical coordinates is decided once, when a track starts (no
    ``prev``), and kept: those whose formation is line-like (second singular value <=
    axis_ratio x the first) with the beacon more than 3 formation lengths from its axis.
    The others -- a formation spread in two dimensions, or a beacon near or inside the
    formation, where the coordinates would be singular -- keep plain ECEF (cart True)."""
    m = mask[..., None]
    n = mask.sum(axis=-1)
    c = _sum(upos * m, axis=-2) / np.maximum(n, 1)[:, None]
    d = (upos - c[:, None, :]) * m
    w2, vec = np.linalg.eigh(np.swapaxes(d, -1, -2) @ d)  # ascending eigenvalues (singular values^2)
    a = vec[..., :, 2]
    line_like = w2[:, 1] <= axis_ratio ** 2 * w2[:, 2]
    if prev is not None:
        a = np.where((_sum(a * prev.a, axis=-1) < 0)[:, None], -a, a)
        keep_c = n < 2
        keep_a = keep_c | ~line_like
        c = np.where(keep_c[:, None], prev.c, c)
        a = np.where(keep_a[:, None], prev.a, a)
    w = beacon_pos - c
    w = w - _sum(w * a, axis=-1, keepdims=True) * a
    rho = np.sqrt(_sum(w * w, axis=-1))
    if prev is None:
        extent = np.max(np.sqrt(_sum(d * d, axis=-1)), axis=-1)
        cart = ~(line_like & (rho > 3.0 * extent) & (n >= 2))
    else:
        cart = np.asarray(prev.cart, bool)
    pos = rho > 0
    if pos.all():  # the usual case: _any_normal's values would all be discarded
        e1 = w / rho[:, None]
    else:
        e1 = np.where(pos[:, None], w / np.where(pos, rho, 1.0)[:, None], _any_normal(a))
    return Frame(c, a, e1, _cross(a, e1), cart)


def _any_normal(a):
    """A unit vector normal to each a (..., 3)."""
    t = np.where((np.abs(a[..., 0]) < 0.9)[..., None], np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    return _unit(t - _sum(t * a, axis=-1, keepdims=True) * a)


def _basis(phi, fr: Frame):
    cp, sp = np.cos(phi)[..., None], np.sin(phi)[..., None]
    return cp * fr.e1 + sp * fr.e2, -sp * fr.e1 + cp * fr.e2


def cyl_to_ecef(y, fr: Frame, jacobian: bool = False):
    """ECEF [B, V] (..., 6) of states y (..., 6) (frames broadcast against the last batch
    axis; rows with fr.cart are ECEF already); with ``jacobian`` also d x / d y (..., 6, 6)."""
    s, rho = y[..., 0:1], y[..., 1:2]
    er, ep = _basis(y[..., 2], fr)
    a = fr.a
    cart = fr.cart[..., None]
    x = np.concatenate([fr.c + s * a + rho * er, y[..., 3:4] * a + y[..., 4:5] * er + y[..., 5:6] * ep], axis=-1)
    any_cart = bool(fr.cart.any())
    if any_cart:
        x = np.where(cart, y, x)
    if not jacobian:
        return x
    J = np.zeros(y.shape[:-1] + (6, 6))
    J[..., 0:3, 0] = a
    J[..., 0:3, 1] = er
    J[..., 0:3, 2] = rho * ep
    J[..., 3:6, 2] = y[..., 4:5] * ep - y[..., 5:6] * er
    J[..., 3:6, 3] = a
    J[..., 3:6, 4] = er
    J[..., 3:6, 5] = ep
    return x, (np.where(cart[..., None], np.eye(6), J) if any_cart else J)


def ecef_to_cyl(x, fr: Frame, jacobian: bool = False):
    """States (..., 6) of ECEF [B, V] (..., 6) (unchanged in rows with fr.cart); with
    ``jacobian`` also (d y / d x, d x / d y) (..., 6, 6) at that point (exact inverses)."""
    d = x[..., 0:3] - fr.c
    s = _sum(d * fr.a, axis=-1)
    w = d - s[..., None] * fr.a
    rho = np.sqrt(_sum(w * w, axis=-1))
    rho_s = np.where(rho > 0, rho, 1.0)
    phi = np.arctan2(_sum(w * fr.e2, axis=-1), _sum(w * fr.e1, axis=-1))
    er = w / rho_s[..., None]
    ep = _cross(fr.a, er)
    v = x[..., 3:6]
    vr, vp = _sum(v * er, axis=-1), _sum(v * ep, axis=-1)
    y = np.empty(s.shape + (6,))
    y[..., 0], y[..., 1], y[..., 2], y[..., 3], y[..., 4], y[..., 5] = s, rho, phi, _sum(v * fr.a, axis=-1), vr, vp
    cart = fr.cart[..., None]
    y = np.where(cart, x, y)
    if not jacobian:
        return y
    a = np.broadcast_to(fr.a, er.shape)
    J = np.zeros(y.shape[:-1] + (6, 6))
    J[..., 0:3, 0], J[..., 0:3, 1], J[..., 0:3, 2] = a, er, rho[..., None] * ep
    J[..., 3:6, 2] = vr[..., None] * ep - vp[..., None] * er
    J[..., 3:6, 3], J[..., 3:6, 4], J[..., 3:6, 5] = a, er, ep
    # inverse: position rows a', er', ep'/rho; velocity rows R' = [a, er, ep]' plus the phi coupling
    Ji = np.zeros_like(J)
    Ji[..., 0, 0:3], Ji[..., 1, 0:3], Ji[..., 2, 0:3] = a, er, ep / rho_s[..., None]
    Ji[..., 3, 3:6], Ji[..., 4, 3:6], Ji[..., 5, 3:6] = a, er, ep
    # v = R(phi)' V: d v / d B = (dR'/dphi V) dphi/dB = [0, v_phi, -v_rho]' ep' / rho
    Ji[..., 4, 0:3] = vp[..., None] * ep / rho_s[..., None]
    Ji[..., 5, 0:3] = -vr[..., None] * ep / rho_s[..., None]
    eye = np.eye(6)
    return y, np.where(cart[..., None], eye, Ji), np.where(cart[..., None], eye, J)


def _sigma_points(y, P):
    n = y.shape[-1]
    L = np.linalg.cholesky(P) * math.sqrt(_UT_C2)
    Lt = np.moveaxis(L, -1, 0)  # (n, T, n): the columns
    return np.concatenate([y[None], y[None] + Lt, y[None] - Lt]), _ut_weights(n)


@functools.lru_cache(maxsize=8)
def _ut_weights(n: int) -> np.ndarray:
    w = np.r_[0.0, np.full(2 * n, 0.5 / _UT_C2)]
    w.flags.writeable = False
    return w


def ut_to_ecef(y, P, fr: Frame):
    """ECEF mean (T, 6) and covariance (T, 6, 6) of the cylindrical Gaussian (y, P): the
    unscented transform (sigma points +-sqrt(6) sigma, W0 = 0): the banana's moments."""
    X, W = _sigma_points(y, P)
    xs = cyl_to_ecef(X, fr)
    m = np.einsum("k,kti->ti", W, xs)
    d = xs - m
    C = np.einsum("k,kti,ktj->tij", W, d, d)
    return m, 0.5 * (C + np.swapaxes(C, -1, -2))


# --------------------------------------------------------------------------- filter steps
