"""One step of the continuous solver's integrators, its error norm, and event location on a step's interpolant.

Every function works on a batch of agents, each with its own step size `H` `(k,)`. `flow(P)` evaluates the
flow map at states `P` `(k, n)` (the agents' discrete state fixed by the caller).

- :func:`dopri5_step`: Dormand–Prince 5(4) (the tableau of MATLAB's ode45 / scipy's RK45), explicit;
- :func:`rosenbrock23_step`: Shampine & Reichelt's L-stable modified Rosenbrock 2(3) (MATLAB's `ode23s`), a
  W-method (second order for any Jacobian estimate `J`), for the stiff barrier along a wedge's face;
- :func:`hermite` / :func:`locate`: the step's cubic Hermite interpolant and the first time on it where a
  condition holds (bisection).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

Flow = Callable[[np.ndarray], np.ndarray]

_C = np.array([0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0])
_A = [
    [],
    [1 / 5],
    [3 / 40, 9 / 40],
    [44 / 45, -56 / 15, 32 / 9],
    [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729],
    [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656],
    [35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84],
]
_B5 = np.array([35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0.0])
_B4 = np.array([5179 / 57600, 0.0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40])
_E = _B5 - _B4
_ROS_D, _ROS_E32 = 1.0 / (2.0 + math.sqrt(2.0)), 6.0 + math.sqrt(2.0)
BISECT = 22  # halvings of a step when locating an event: 2.4e-7 of the step


def error_norm(err_vec: np.ndarray, P: np.ndarray, P1: np.ndarray, rtol: float, atol: float) -> np.ndarray:
    """RMS of the error estimate scaled by `atol + rtol |p|` (<= 1: the step is accepted)."""
    z = err_vec / (atol + rtol * np.maximum(np.abs(P), np.abs(P1)))
    return np.sqrt((z * z).sum(axis=1) / z.shape[1])


def dopri5_step(flow: Flow, P: np.ndarray, F0: np.ndarray, H: np.ndarray):
    """`(P1, F1, err_vec, evaluations)`: the 5th-order solution, the flow there (FSAL) and the embedded error."""
    K = [F0]
    for i in range(1, 6):
        K.append(flow(P + H[:, None] * sum(a * K[j] for j, a in enumerate(_A[i]) if a != 0.0)))
    P1 = P + H[:, None] * sum(a * K[j] for j, a in enumerate(_A[6]) if a != 0.0)  # 5th order (row 7 = B5)
    F1 = flow(P1)
    K.append(F1)
    err_vec = H[:, None] * sum(c * K[j] for j, c in enumerate(_E) if c != 0.0)
    return P1, F1, err_vec, 6


def jacobian(flow: Flow, P: np.ndarray, F: np.ndarray) -> np.ndarray:
    """`dF/dp` `(k, n, n)` by forward differences (`n` flow evaluations)."""
    k, n = P.shape
    J = np.empty((k, n, n))
    eps = 1e-7 * np.maximum(1.0, np.abs(P))
    for c in range(n):
        Pc = P.copy()
        Pc[:, c] += eps[:, c]
        J[:, :, c] = (flow(Pc) - F) / eps[:, c : c + 1]
    return J


def _w_solver(J: np.ndarray, hd: np.ndarray):
    """`b -> W^{-1} b` for `W = I - hd J` (closed form in 2-D, batched LU otherwise)."""
    if J.shape[1] == 2:
        w00, w01 = 1.0 - hd * J[:, 0, 0], -hd * J[:, 0, 1]
        w10, w11 = -hd * J[:, 1, 0], 1.0 - hd * J[:, 1, 1]
        det = w00 * w11 - w01 * w10

        def solve(b):
            return np.stack([(w11 * b[:, 0] - w01 * b[:, 1]) / det, (w00 * b[:, 1] - w10 * b[:, 0]) / det], axis=1)

        return solve
    W = np.eye(J.shape[1])[None] - hd[:, None, None] * J
    return lambda b: np.linalg.solve(W, b[..., None])[..., 0]


def rosenbrock23_step(flow: Flow, P: np.ndarray, F0: np.ndarray, H: np.ndarray, J: np.ndarray):
    """`(P1, F1, err_vec, evaluations)` of one modified Rosenbrock 2(3) step with Jacobian estimate `J`."""
    solve = _w_solver(J, H * _ROS_D)
    k1 = solve(F0)
    F1m = flow(P + 0.5 * H[:, None] * k1)
    k2 = solve(F1m - k1) + k1
    P1 = P + H[:, None] * k2
    F2 = flow(P1)
    k3 = solve(F2 - _ROS_E32 * (k2 - F1m) - 2.0 * (k1 - F0))
    err_vec = (H / 6.0)[:, None] * (k1 - 2.0 * k2 + k3)
    return P1, F2, err_vec, 2


def hermite(p0, f0, p1, f1, h, theta):
    """Cubic Hermite interpolant of a step at fractions `theta` `(k,)`."""
    t2, t3 = theta * theta, theta * theta * theta
    h00, h10, h01, h11 = 2 * t3 - 3 * t2 + 1, t3 - 2 * t2 + theta, -2 * t3 + 3 * t2, t3 - t2
    return (h00[:, None] * p0 + (h10 * h)[:, None] * f0 + h01[:, None] * p1 + (h11 * h)[:, None] * f1)


def locate(cond, p0, f0, p1, f1, h, hi=None):
    """First fraction `theta` in (0, hi] where `cond` holds (false at 0, true at `hi`, default 1), by bisection.

    Returns `theta_hi` (cond true there) so that the event state satisfies the event's condition.
    """
    lo = np.zeros(len(h))
    hi = np.ones(len(h)) if hi is None else np.array(hi, dtype=float)
    for _ in range(BISECT):
        mid = 0.5 * (lo + hi)
        c = cond(hermite(p0, f0, p1, f1, h, mid))
        hi = np.where(c, mid, hi)
        lo = np.where(c, lo, mid)
    return hi
