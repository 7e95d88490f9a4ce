"""The seed 000 variant-2 measurement models (the code-minus-carrier increment rows) and the edits
of the state vector when states are appended or marginalised (variants 2 and 3); the runner is
sitl.app.experiments.iono_tropo_filters.run_streamed.

Noise bookkeeping: code and phase noise are white per epoch. E_j(t) = 2 I_g k_j dm_j +
eps_D,j(t) - eps_D,j(t - W) + (phase noise): its code noise is the *same* noise as that of
pr_j(t) and of pr_j(t - W), which the filter also uses. Two treatments (`cmc_noise`):
* "states" (default, exact): all satellites' windows run on one grid of W epochs. At a
  window start the code noise eps_D,j of every tracked satellite becomes a state e_j (prior
  N(0, sigma_D^2), constant) and pr_j's row carries it (h += e_j, R = 0: marginally the
  usual pr_j). At the window end, E_j = 2 k_j dm_j I_g + e_j(new) - e_j(old) with variance
  2 sigma_Phi^2 only; then the old e_j are marginalised (dropped) and the new ones start the
  next window. A satellite that sets inside its window just loses its e_j. All correlations
  are carried by the states, so the increment is worth what it is really worth: with pr_j(t)
  and pr_j(t - W) it pins down the carrier-phase change over the window (3 mm) -- the
  information the seed's "noise 2 sigma_D^2" reading throws away (_CodeNoiseStateModel; the
  test checks it against one batch GLS solve with the full noise covariance).
* "whitened" (close to the seed): every B sample enters at most one increment (each
  satellite's epochs alternate between W-long "start" and "end" blocks, staggered across
  satellites; at an end epoch E pairs B(t) with B(t - W) from the preceding start block),
  and E_j(t) is decorrelated from the same epoch's pr_j(t) (row E_j - pr_j, variance
  sigma_D^2 + 2 sigma_Phi^2, see _CmcIncrementModel). Ignored: the correlation with the
  already-processed pr_j(t - W); E then carries only 2 I_g dm_j against ~6 m of noise.
Both: the dm_I error from the filter's position/geocentric elevation (the truth maps with the
geodetic elevation) is ignored.
"""
from __future__ import annotations

import numpy as np

from filters.iono_tropo import IDX_IONO
from filters.models import JointMeasurement

__all__ = []  # private to the seed 000 runner (sitl.app.experiments.iono_tropo_filters)


class _CmcIncrementModel(JointMeasurement):
    """Seed 000 variant 2: the variant-1 model plus one code-minus-carrier increment row per
    satellite in ``rows`` (local indices into the base model's satellites).

    Increment (eq 33): E_j = B_j(t) - B_j(t - W), B_j = pr_j - phase_j, modelled as
    2 k_j dm_j I_g (only the I_g column; dm_j = m_I(eta_j(t)) - m_I(eta_j(t - W)) from the
    filter's own mapping values, treated as known). E_j shares the code noise eps_D,j(t)
    with the same epoch's pseudorange row, cov(pr_j, E_j) = sigma_D^2, var(E_j) =
    2 sigma_D^2 + 2 sigma_Phi^2. That 2x2 block is whitened exactly (Gram-Schmidt, the
    Cholesky factor done by hand) so R stays diagonal: the row carries
        E'_j = E_j - pr_j,  h = 2 k_j dm_j I_g - h_pr,j(x),  H = 2 k_j dm_j e_Ig - H_pr,j,
        var = sigma_D^2 + 2 sigma_Phi^2.
    Where ``used`` (trials, R) is False (not slip-free over the window) the row is inert:
    z = h = 0, H = 0 (no information, no NIS).
    """

    def __init__(self, base, rows, coef, used, var_e):
        self.base = base
        self.rows = rows
        self.coef = np.where(used, coef, 0.0)
        self.used = used
        self.var_e = var_e

    def h_and_H(self, x):
        z, H = self.base.h_and_H(x)
        r, used = self.rows, self.used
        hE = np.where(used, self.coef * x[..., IDX_IONO, None] - z[..., r], 0.0)
        HE = np.where(used[..., None], -H[..., r, :], 0.0)
        HE[..., IDX_IONO] += self.coef
        return np.concatenate([z, hE], axis=-1), np.concatenate([H, HE], axis=-2)

    def R_diag(self):
        rb = self.base.R_diag()
        batch = self.used.shape[:-1]
        rb = np.broadcast_to(rb, batch + rb.shape[-1:])
        re = np.broadcast_to(self.var_e, self.used.shape)
        return np.concatenate([rb, re], axis=-1)


class _CodeNoiseStateModel(JointMeasurement):
    """Seed 000 variant 2 with the code noise at the window start as states (cmc_noise="states").

    x = [11 base states, e_1 .. e_M]: e_i is the code noise eps_D of one satellite at the
    epoch its window started (a constant once drawn; prior N(0, sigma_D^2)). Rows:
    * pr_j, prr_j as in IonoTropoGnss (``base``, built with n_state = len(x)); where
      ``pr_cols[j] >= 0`` the window of satellite j starts now, pr_j's noise is the state
      e = x[pr_cols[j]] (h += e, H[e] = 1) and its R entry is 0: marginalised over e that is
      exactly the usual pr_j with variance sigma_D^2;
    * one increment row per (local satellite ``inc_rows[r]``) whose window ends now:
        E_j = B_j(t) - B_j(t - W) = 2 k_j dm_j I_g + e_new - e_old + (phase noise),
      e_new = x[inc_new[r]] the code noise of this epoch (the same state as pr_j's, so the
      correlation with pr_j(t) is carried), e_old = x[inc_old[r]] the one at the window
      start (correlated with everything that pr_j(t - W) told the filter), variance
      var_e = 2 sigma_Phi^2. Where ``used`` is False (a slip in the window) the row is inert.
    """

    def __init__(self, base, pr_cols, inc_rows, inc_new, inc_old, coef, used, var_e):
        self.base = base
        self.pr_cols = pr_cols
        self.inc_rows, self.inc_new, self.inc_old = inc_rows, inc_new, inc_old
        self.coef = np.where(used, coef, 0.0)
        self.used = used
        self.var_e = var_e

    def h_and_H(self, x):
        z, H = self.base.h_and_H(x)
        z = np.array(z, dtype=float)
        H = np.array(np.broadcast_to(H, x.shape[:-1] + H.shape[-2:]), dtype=float)
        rows = np.flatnonzero(self.pr_cols >= 0)
        cols = self.pr_cols[rows]
        z[..., rows] += x[..., cols]
        H[..., rows, cols] = 1.0
        if self.inc_rows.size == 0:
            return z, H
        used = self.used
        R = self.inc_rows.size
        hE = np.where(used, self.coef * x[..., IDX_IONO, None] + x[..., self.inc_new] - x[..., self.inc_old], 0.0)
        HE = np.zeros(x.shape[:-1] + (R, x.shape[-1]))
        HE[..., IDX_IONO] = self.coef
        r = np.arange(R)
        HE[..., r, self.inc_new] = np.where(used, 1.0, 0.0)
        HE[..., r, self.inc_old] = np.where(used, -1.0, 0.0)
        return np.concatenate([z, hE], axis=-1), np.concatenate([H, HE], axis=-2)

    def R_diag(self):
        batch = self.used.shape[:-1]
        rb = np.array(np.broadcast_to(self.base.R_diag(), batch + np.shape(self.base.R_diag())[-1:]), dtype=float)
        rb[..., np.flatnonzero(self.pr_cols >= 0)] = 0.0
        re = np.broadcast_to(self.var_e, self.used.shape)
        return np.concatenate([rb, re], axis=-1)


def _drop_states(x, P, cols):
    keep = np.setdiff1d(np.arange(x.shape[-1]), cols)
    return x[:, keep], P[:, keep][:, :, keep]


def _append_states(x, P, m):
    n = x.shape[-1]
    x2 = np.zeros((x.shape[0], n + m))
    x2[:, :n] = x
    P2 = np.zeros((x.shape[0], n + m, n + m))
    P2[:, :n, :n] = P
    return x2, P2
