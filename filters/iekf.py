"""Iterated extended Kalman update (Gauss-Newton on the measurement), batched.

After a first EKF update x_1 (linearised at the prior x-), each iteration relinearises the
measurement at the current iterate x_i and updates the PRIOR again (Bell & Cathey 1993):

    nu_i = z - h(x_i) - H_i (x- - x_i),   H_i = dh/dx at x_i
    K_i  = P- H_i' (H_i P- H_i' + R)^-1
    x_{i+1} = x- + K_i nu_i,    P_{i+1} = (I - K_i H_i) P- (I - K_i H_i)' + K_i R K_i'

x_{i+1} is a Gauss-Newton step on (x - x-)' P-^-1 (x - x-) + (z - h(x))' R^-1 (z - h(x)),
so the fixed point is the maximum a posteriori state of the epoch. The update itself is the
caller's (``update``: a Joseph update, a gated one with the gate decided at the first
iterate, a Schmidt update, ...), and so is the linearisation (``linearize``, which may hold
some rows at their first linearisation): this function is the loop and its stopping rules.

Stopping rules (each optional), checked for the whole batch at once (a batch iterates as one
problem: every row stops at the same iteration):

* the step: no component of ``point(x_i) - point(x_{i-1})`` is ``step_tol`` or more in
  absolute value (x_0 = x-; ``point`` maps a state to the coordinates where the tolerance is
  meant, identity by default; ``point_prior`` is point(x-) when the caller has it already)
  -- checked before relinearising at x_i: a further update would relinearise at the same point;
* the innovation: no |nu_i - nu_{i-1}| / ``sigma`` is ``innovation_tol`` or more where
  ``innovation_rows`` (broadcast against nu) is True (nu_0 = ``nu_prior``, the first update's
  innovation z - h(x-)) -- checked before updating with nu_i: the update would repeat the last.

Pure: no state, no I/O.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

__all__ = ["IteratedUpdate", "iterated_update", "relinearized_innovation"]


class IteratedUpdate(NamedTuple):
    result: object  # the last iterated update's result; None when none ran (the first update stands)
    updates: int  # updates made, the first included (1: no iteration ran)


def relinearized_innovation(z, hx, H, x_prior, x):
    """nu = z - h(x) - H (x- - x) with h(x) = hx (..., m), H (..., m, n) at the iterate x.

    x_prior and x (..., n) broadcast against H's batch axes (pass x[:, None] for H with a
    per-observer axis (T, N, m, n))."""
    return z - hx - np.einsum("...ai,...i->...a", H, x_prior - x)


def iterated_update(x, x1, linearize: Callable, update: Callable, iterations: int, *,
                    step_tol: float | None = None, point: Callable | None = None, point_prior=None,
                    innovation_tol: float | None = None, nu_prior=None, sigma=None,
                    innovation_rows=None) -> IteratedUpdate:
    """The iterations after a first update (module docstring); at most ``iterations - 1`` of them.

    x (..., n): the prior mean x-; x1: the first update's mean.
    linearize(x_i) -> (nu_i, H_i): the relinearised innovation (relinearized_innovation) and
        Jacobian, in the form ``update`` takes them.
    update(nu_i, H_i) -> a result whose first item is the new mean x_{i+1}: the update of the
        prior (x-, P-) with nu_i and H_i.
    step_tol, point, point_prior; innovation_tol, nu_prior, sigma, innovation_rows: the
        stopping rules (module docstring); None: not applied.
    Returns IteratedUpdate(result of the last update or None, number of updates).
    """
    if step_tol is not None:
        last_point = (point(x) if point is not None else x) if point_prior is None else point_prior
    if innovation_tol is not None:
        if nu_prior is None or sigma is None:
            raise ValueError("the innovation rule needs nu_prior and sigma")
        nu_last = nu_prior
    xi, result, updates = x1, None, 1
    for _ in range(int(iterations) - 1):
        if step_tol is not None:
            p = point(xi) if point is not None else xi
            if np.max(np.abs(p - last_point)) < step_tol:
                break
            last_point = p
        nu, H = linearize(xi)
        if innovation_tol is not None:
            d = np.abs(nu - nu_last) / sigma
            if innovation_rows is not None:
                d = np.where(innovation_rows, d, 0.0)
            if np.max(d, initial=0.0) < innovation_tol:
                break
            nu_last = nu
        result = update(nu, H)
        xi = result[0]
        updates += 1
    return IteratedUpdate(result, updates)
