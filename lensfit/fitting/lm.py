"""A Levenberg-Marquardt solver for many small least-squares problems at once (JAX, float64).

Why not optimistix here: the edge estimator solves hundreds of 5-7 parameter problems per
stack, all of one shape. Under ``jax.vmap`` a general solver's trace is large (seconds per
shape, in every new process: tracing is not kept by the persistent compilation cache) and its
``while`` loop runs every problem of a batch until the slowest one stops. This loop is one small
body (a few hundred milliseconds to trace), solves the damped normal equations of each problem
by Cholesky, and stops for a whole batch once every problem has stopped improving or after
``max_steps``. The CoC fit (one problem per stack) keeps optimistix.

Algorithm (Moré 1978, as in MINPACK's lmder, without its trust-region scaling updates): at
``theta`` with residuals ``r`` and Jacobian ``J`` (forward mode), the step solves
``(J^T J + lambda diag(J^T J)) delta = -J^T r`` (equilibrated, by Cholesky); a step that lowers the sum of squares is taken
and ``lambda`` divided by 3, otherwise ``lambda`` multiplied by 10. A problem has converged when a
step moves no parameter by more than ``rtol`` of its size plus ``atol``, when a lightly damped
step (``lambda <= 1``) lowers the cost, or would by the quadratic model, by less than
``ftol + rtol * cost``, or when no step
lowers the cost any more.
Inside ``vmap`` a converged problem keeps its values while the others go on.

Reference: J. J. Moré, "The Levenberg-Marquardt algorithm: implementation and theory",
Numerical Analysis, Lecture Notes in Mathematics 630 (1978).
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp

LAMBDA_START = 1e-3
LAMBDA_DOWN = 1.0 / 3.0
LAMBDA_UP = 10.0
LAMBDA_MAX = 1e12
DIAG_FLOOR_REL = 1e-12


def _equilibrated_cholesky(A, lam, floor_rel: float):
    """``(s, L)``: ``s`` = 1 / sqrt of the diagonal of A (floored at ``floor_rel`` of its largest
    element) and ``L`` the Cholesky factor of ``s A s + lam I``: parameters whose scales differ by
    1e10 (an edge's level and its blur's squared radius) would otherwise lose every digit of the
    small ones."""
    diag = jnp.diag(A)
    s = 1.0 / jnp.sqrt(jnp.maximum(diag, floor_rel * jnp.max(diag) + 1e-300))
    M = s[:, None] * A * s[None, :] + lam * jnp.eye(A.shape[0], dtype=A.dtype)
    return s, jnp.linalg.cholesky(M)


def _scaled_solve(A, g, lam):
    """``(A + lam D)^-1 g``, ``D`` the diagonal of A floored at ``DIAG_FLOOR_REL`` of its largest
    element: the floor keeps a direction the data do not determine (curvature at rounding level)
    from taking huge steps on rounding noise."""
    s, L = _equilibrated_cholesky(A, lam, DIAG_FLOOR_REL)
    return s * jax.scipy.linalg.cho_solve((L, True), s * g)


def covariance(J, ridge: float = 1e-10):
    """``(J^T J)^-1`` with a ``ridge`` relative to each parameter's own curvature: a direction the
    data do not determine gets a huge variance, where a truncated pseudo-inverse would give it
    none (and a reading a false precision)."""
    A = J.T @ J
    s, L = _equilibrated_cholesky(A, ridge, 0.0)
    inv = jax.scipy.linalg.cho_solve((L, True), jnp.eye(A.shape[0], dtype=A.dtype))
    return s[:, None] * inv * s[None, :]


def residuals_and_jacobian(residuals: Callable[[Any, Any], Any], theta, args):
    """``(r, J)`` at ``theta`` in one forward-mode pass."""
    J, r = jax.jacfwd(lambda t: (residuals(t, args),) * 2, has_aux=True)(theta)
    return r, J


def least_squares(residuals: Callable[[Any, Any], Any], theta0, args, *, max_steps: int = 60,
                  rtol: float = 1e-9, atol: float = 1e-12, ftol: float = 0.0, gtol: float = 1e-6):
    """Minimise ``sum(residuals(theta, args)**2)`` from ``theta0`` (one problem; ``jax.vmap`` it).

    Returns ``(theta, cost, converged)``: ``converged`` is False when ``max_steps`` ran out while
    a Gauss-Newton step could still gain more than ``gtol * cost + ftol`` (the cost is then still
    the lowest found), or the cost is not finite.
    """

    def cost_of(theta):
        r = residuals(theta, args)
        return jnp.sum(r * r)

    def step(state):
        theta, lam, cost, i, done = state
        r, J = residuals_and_jacobian(residuals, theta, args)
        A = J.T @ J
        g = J.T @ r
        delta = -_scaled_solve(A, g, lam)
        trial = theta + delta
        new_cost = cost_of(trial)
        better = jnp.isfinite(new_cost) & (new_cost < cost) & jnp.all(jnp.isfinite(delta))
        small_step = jnp.all(jnp.abs(delta) <= rtol * jnp.abs(theta) + atol)
        # A Gauss-Newton step (little damping) that gains less than ``ftol`` in the sum of squares:
        # with residuals in standard errors the parameters are then within sqrt(ftol) standard
        # errors of the minimum.
        small_gain = better & (lam <= 1.0) & (cost - new_cost <= ftol + rtol * cost)
        # ... or that promises less than that (-g.delta: the decrease the quadratic model predicts
        # for the undamped step, nearly this one when lambda <= 1).
        small_gain = small_gain | ((lam <= 1.0) & (-jnp.dot(g, delta) <= ftol + rtol * cost))
        # At the minimum every step is tiny (taken or not); damping without bound means no step
        # lowers the cost any more (a minimum to rounding).
        done_now = done | small_gain | small_step | (lam > LAMBDA_MAX) | (cost == 0.0)
        theta = jnp.where(better, trial, theta)
        cost = jnp.where(better, new_cost, cost)
        lam = jnp.where(better, lam * LAMBDA_DOWN, lam * LAMBDA_UP)
        return theta, lam, cost, i + 1, done_now

    def more(state):
        return (~state[4]) & (state[3] < max_steps)

    theta0 = jnp.asarray(theta0)
    state = (theta0, jnp.asarray(LAMBDA_START, theta0.dtype), cost_of(theta0), 0, jnp.asarray(False))
    theta, _, cost, _, done = jax.lax.while_loop(more, step, state)
    # Out of steps: still converged if no quadratic-model step could gain more than ``gtol`` of
    # the cost (a flat valley, where any point is as good: the covariance shows it).
    r, J = residuals_and_jacobian(residuals, theta, args)
    A = J.T @ J
    g = J.T @ r
    decrement = g @ _scaled_solve(A, g, 1e-9)
    flat = jnp.isfinite(decrement) & (decrement <= gtol * cost + ftol)
    return theta, cost, (done | flat) & jnp.isfinite(cost)
