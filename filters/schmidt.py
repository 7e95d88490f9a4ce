"""Schmidt (consider) Kalman update with per-sensor consider states, batched.

A consider state is one the measurements depend on but the filter does not estimate (Schmidt
1966; Tapley, Schutz & Born 2004, sec. 6.4): here each of N sensors g has its own, eps_g (k,),
e.g. the navigation error of the observer that made the measurement. The filter carries the
cross-covariances C_g = Cov(x error, eps_g) (n, k); Cov(eps_g) = Pc_g is given, and the
sensors' consider states are independent of each other. Sensor g's r measurement rows:

    z_g = h_g(x) + J_g eps_g + v_g,   v_g ~ N(0, R_g);   H_g = dh_g/dx (r, n),  J_g (r, k)

Stacked over the sensors (m = N r rows; H = [H_1; ...; H_N]), with X = [C_1 J_1', ..., C_N J_N']
(n, m) = Cov(x error, J eps):

    S  = H P H' + H X + X' H' + blockdiag(J_g Pc_g J_g' + R_g)
    K  = (P H' + X) S^-1            the gain of the state; the consider states' gain is 0
    x+ = x + K nu,   P+ = P - K (P H' + X)'
    C_g+ = C_g - K (H C_g + E_g J_g Pc_g)      E_g: sensor g's rows of the identity (m, r)

This is the full Kalman update of the joint state [x, eps_1, ..., eps_N] with the rows of the
gain for the eps_g set to 0 (in Joseph form that is exact for any gain; P+ above is its value for
the optimal K of x), and Pc stays as it was: the filter does not learn the consider states, it
only keeps its memory of them. With C = 0 it is the ordinary update with R_g + J_g Pc_g J_g'.

Only the sensors with ``used`` True are updated with (a used sensor's rows, the others inert: S
with identity blocks and zero gain columns for them, so that an absent sensor's block, which
can be indefinite, is never factored). nis = nu_u' S_u^-1 nu_u over the used rows (NaN where
none is used).

Shapes: x (..., n), P (..., n, n), C (..., N, n, k), nu (..., N, r), H (..., N, r, n),
J (..., N, r, k), Pc (..., N, k, k), R (..., N, r, r), used (..., N) bool. Pure numpy.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = ["SchmidtInnovation", "SchmidtUpdate", "schmidt_innovation", "schmidt_update"]


class SchmidtInnovation(NamedTuple):
    S: np.ndarray  # (..., m, m) innovation covariance, m = N r
    X: np.ndarray  # (..., n, m) [C_g J_g']: Cov(x error, J eps)
    S_blocks: np.ndarray  # (..., N, r, r) each sensor's own block of S (its gate)


class SchmidtUpdate(NamedTuple):
    x: np.ndarray  # (..., n)
    P: np.ndarray  # (..., n, n)
    C: np.ndarray  # (..., N, n, k) the cross-covariances with the consider states
    nis: np.ndarray  # (...,)


def schmidt_innovation(P, C, H, J, Pc, R) -> SchmidtInnovation:
    """S = H P H' + H X + X' H' + blockdiag(J_g Pc_g J_g' + R_g) and X = [C_g J_g'] (module docstring)."""
    P, C, H, J, Pc, R = (np.asarray(a, dtype=float) for a in (P, C, H, J, Pc, R))
    batch = P.shape[:-2]
    T = math.prod(batch)
    N, r, n = H.shape[-3:]
    m = N * r
    P, C, H, J, Pc, R = (a.reshape((T,) + a.shape[len(batch):]) for a in (P, C, H, J, Pc, R))
    X = np.einsum("tnia,tnba->tinb", C, J).reshape(T, n, m)  # C_g J_g'
    Hs = H.reshape(T, m, n)
    D = np.einsum("tnai,tnij,tnbj->tnab", J, Pc, J) + R
    HX = Hs @ X
    S = Hs @ P @ np.swapaxes(Hs, -1, -2) + HX
    S = np.ascontiguousarray(S + np.swapaxes(HX, -1, -2))
    g = np.arange(N)
    Sb = S.reshape(T, N, r, N, r)
    Sb[:, g, :, g, :] += np.moveaxis(D, 1, 0)
    S_blocks = np.moveaxis(Sb[:, g, :, g, :], 0, 1)  # (T, N, r, r)
    return SchmidtInnovation(S.reshape(batch + (m, m)), X.reshape(batch + (n, m)),
                             S_blocks.reshape(batch + (N, r, r)))


def schmidt_update(x, P, C, nu, H, J, Pc, innovation: SchmidtInnovation, used) -> SchmidtUpdate:
    """The Schmidt update of the used sensors' rows (module docstring), from schmidt_innovation's
    S and X for the same P, C, H, J, Pc."""
    x, P, C, nu, H, J, Pc = (np.asarray(a, dtype=float) for a in (x, P, C, nu, H, J, Pc))
    batch = x.shape[:-1]
    T = math.prod(batch)
    n = x.shape[-1]
    N, r = nu.shape[-2:]
    k = J.shape[-1]
    m = N * r
    x, P, C, nu, H, J, Pc = (a.reshape((T,) + a.shape[len(batch):]) for a in (x, P, C, nu, H, J, Pc))
    S = innovation.S.reshape(T, m, m)
    X = innovation.X.reshape(T, n, m)
    used = np.broadcast_to(np.asarray(used, dtype=bool), batch + (N,)).reshape(T, N)
    Hs = H.reshape(T, m, n)
    u = np.repeat(used, r, axis=1).astype(float)
    Su = S * u[:, :, None] * u[:, None, :] + np.eye(m) * (1.0 - u)[:, None, :]
    M = (P @ np.swapaxes(Hs, -1, -2) + X) * u[:, None, :]  # P H' + X, used columns
    nuu = nu.reshape(T, m) * u
    Si_nu = np.linalg.solve(Su, nuu[..., None])[..., 0]
    K = np.swapaxes(np.linalg.solve(Su, np.swapaxes(M, -1, -2)), -1, -2)  # M S^-1 (S symmetric)
    x1 = x + np.einsum("tij,tj->ti", M, Si_nu)
    P1 = P - K @ np.swapaxes(M, -1, -2)
    P1 = 0.5 * (P1 + np.swapaxes(P1, -1, -2))
    # Cov(nu, eps_g) (T, N, m, k): H C_g, plus J_g Pc_g in sensor g's own rows; used rows only
    G = np.ascontiguousarray(np.einsum("tmk,tnkb->tnmb", Hs * u[..., None], C))
    Gb = G.reshape(T, N, N, r, k)
    g = np.arange(N)
    Gb[:, g, g] += np.einsum("tnai,tnib->tnab", J, Pc) * used[..., None, None]
    C1 = C - np.einsum("tkm,tnmb->tnkb", K, G)
    nis = np.where(used.any(axis=-1), np.sum(nuu * Si_nu, axis=-1), np.nan)
    return SchmidtUpdate(x1.reshape(batch + (n,)), P1.reshape(batch + (n, n)), C1.reshape(batch + (N, n, k)),
                         nis.reshape(batch))
