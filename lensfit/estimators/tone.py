"""A developed image's processing fitted from a stack's own edges: the tone curve and the
sharpening a raw developer or a camera's JPEG engine applied, forward-modelled in the edge fit
(``lensfit.measurement.processing`` decides where it is needed and whether its readings are
kept).

In linear light a lens draws an edge as ``lo + (hi - lo) E(x; R)``, ``E`` the pixel-integrated
disk edge (``lensfit.measurement.psf``). A developer maps light through a monotone tone curve
and sharpens the result; the file holds::

    u(x) = S[ T(lo + (hi - lo) E(x - x0; R)) ]

- ``T`` is the declared encoding (sRGB or none) warped by ``W(v) = v + sum_k c_k sin(k pi v)``
  on its [0, 1] scale, one curve for the whole stack (its first ``terms`` sine terms);
- ``S`` is an unsharp mask on the encoded values, ``u + a (u - g_sigma * u)``, ``g_sigma`` a
  Gaussian, one amount ``a`` and radius ``sigma`` for the stack (a negative amount is a blur).

Every edge has its own position, squared radius, levels and turn (as the edge estimator's
uniform disk); the curve and the mask are shared. What pins them apart from the blur: a tone
curve relabels the levels of an edge but cannot move where its profile starts and stops
changing, which is the disk's diameter (a disk's edge has a compact support), and one curve
must serve edges of every blur at once; halos beside the edges are the mask's. The joint
least-squares problem (thousands of residuals, a few per edge, a handful shared) is solved by
Levenberg-Marquardt on the normal equations reduced to the shared parameters (the Schur
complement of the edges' 5 x 5 blocks). The shared parameters' covariance, and how each edge's
radius moves with them, are returned so that their uncertainty reaches the f-number.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from lensfit.measurement.psf import pixel_edge_profile

#: The grid the mask's blurred copy is computed on, per edge: this many points over the
#: profile's reach and ``GRID_MARGIN_SIGMA`` sigmas beyond it.
GRID_POINTS = 512
GRID_MARGIN_SIGMA = 5.0
#: Bins per edge (a profile's first ``BINS`` of those within ``REACH_PX`` of its line).
BINS = 256
REACH_PX = 60.0
#: Edges per compiled call: a stack's are padded to a multiple (with edges of no weight).
BLOCK = 64
#: Weak priors (1 sigma) that hold the shared parameters where the edges do not ask for them:
#: a warp term, the mask's amount, the log of its radius about ``SIGMA_PRIOR_PX``.
WARP_PRIOR = 0.5
AMOUNT_PRIOR = 2.0
LOG_SIGMA_PRIOR = 1.0
SIGMA_PRIOR_PX = 1.0
MAX_STEPS = 80
#: Edges the curve and mask are fitted on (spread over the stack); the rest are read with them held.
JOINT_EDGES = 240


def _srgb(v):
    v = jnp.maximum(v, -0.01)
    return jnp.where(v <= 0.0031308, 12.92 * v, 1.055 * jnp.abs(v) ** (1.0 / 2.4) - 0.055)


def encoded(values: np.ndarray, encoding: str) -> tuple[np.ndarray, np.ndarray]:
    """A profile's linear values back on its file's scale, and the slope of that map (which
    turns each bin's standard error to the file's scale)."""
    v = np.asarray(values, np.float64)
    if encoding != "srgb":
        return v, np.ones_like(v)
    c = np.clip(v, 1e-5, None)
    u = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1.0 / 2.4) - 0.055)
    slope = np.where(c <= 0.0031308, 12.92, 1.055 / 2.4 * c ** (1.0 / 2.4 - 1.0))
    return u, slope


def tone_curve(light, coefficients, srgb: bool):
    """``T``: linear light to the file's scale, through the declared encoding (``srgb``) and the
    warp with sine ``coefficients``."""
    base = _srgb(light) if srgb else light
    k = jnp.arange(1, coefficients.shape[0] + 1, dtype=base.dtype)
    inside = jnp.clip(base, 0.0, 1.0)
    return base + jnp.sum(coefficients[:, None] * jnp.sin(jnp.pi * k[:, None] * inside[None, :]), axis=0)


def _edge_model(p, g, x_scale, d, s, nx, ny, terms: int, srgb: bool):
    # p = (x0, rho = R^2, lo, hi, turn) as the edge estimator's uniform disk; g = (c_1..c_terms,
    # amount, log sigma); x_scale: the half-width of the edge's grid (px).
    x0, rho, lo, hi, turn = (p[i] for i in range(5))
    c, amount, sigma = g[:terms], g[terms], jnp.exp(g[terms + 1])
    R = jnp.sqrt(0.5 * (rho + jnp.sqrt(rho * rho + 1e-12)) + 1e-12)
    x = d - x0 - turn * s
    here = tone_curve(lo + (hi - lo) * pixel_edge_profile(x, R, nx, ny), c, srgb)
    # The Gaussian by FFT over a grid that reaches GRID_MARGIN_SIGMA sigmas beyond the bins: the
    # transform wraps one flat end onto the other only within that margin, off the bins.
    reach = x_scale + GRID_MARGIN_SIGMA * sigma
    grid = jnp.linspace(-reach, reach, GRID_POINTS, endpoint=False)
    on_grid = tone_curve(lo + (hi - lo) * pixel_edge_profile(grid, R, nx, ny), c, srgb)
    frequency = jnp.fft.rfftfreq(GRID_POINTS, d=grid[1] - grid[0])
    spectrum = jnp.fft.rfft(on_grid)
    gauss = jnp.exp(-2.0 * (jnp.pi * sigma * frequency) ** 2).astype(spectrum.dtype)
    blurred = jnp.fft.irfft(spectrum * gauss, n=GRID_POINTS)
    return here + amount * (here - jnp.interp(x, grid, blurred))


def _residuals(p, g, x_scale, d, s, u, w, nx, ny, terms: int, srgb: bool):
    return w * (u - _edge_model(p, g, x_scale, d, s, nx, ny, terms, srgb))


_AXES = (0, None, 0, 0, 0, 0, 0, 0, 0)


@partial(jax.jit, static_argnames=("terms", "srgb"))
def _evaluate(P, g, X, D, S, U, W, NX, NY, terms: int, srgb: bool):
    """Residuals, their Jacobian in each edge's parameters and in the shared ones, for a block."""
    fn = partial(_residuals, terms=terms, srgb=srgb)
    r = jax.vmap(fn, _AXES)(P, g, X, D, S, U, W, NX, NY)
    Jp = jax.vmap(jax.jacfwd(fn, 0), _AXES)(P, g, X, D, S, U, W, NX, NY)
    Jg = jax.vmap(jax.jacfwd(fn, 1), _AXES)(P, g, X, D, S, U, W, NX, NY)
    return r, Jp, Jg


@partial(jax.jit, static_argnames=("terms", "srgb"))
def _cost(P, g, X, D, S, U, W, NX, NY, terms: int, srgb: bool):
    r = jax.vmap(partial(_residuals, terms=terms, srgb=srgb), _AXES)(P, g, X, D, S, U, W, NX, NY)
    return jnp.sum(r * r, axis=1)


@dataclass
class ToneFit:
    """The processing fitted to a stack's edges.

    Attributes
    ----------
    terms : the tone curve's sine terms
    shared : (c_1..c_terms, mask amount, log mask sigma)
    shared_cov : their covariance (widened by the reduced chi-square where above 1)
    chi2_reduced : the joint fit's reduced chi-square
    edges : the edges it rests on
    srgb : whether the curve is a warp of the sRGB encoding (else of the identity)
    """

    terms: int
    shared: np.ndarray
    shared_cov: np.ndarray
    chi2_reduced: float
    edges: int
    srgb: bool

    @property
    def amount(self) -> float:
        return float(self.shared[self.terms])

    @property
    def sigma_px(self) -> float:
        return float(math.exp(self.shared[self.terms + 1]))

    def curve(self, light: np.ndarray, warped: bool = True) -> np.ndarray:
        """The fitted tone curve at linear ``light`` (the file's scale, 0-1); ``warped=False``: the
        declared encoding it warps."""
        coefficients = self.shared[:self.terms] if warped else np.zeros(self.terms)
        with jax.enable_x64(True):
            return np.asarray(tone_curve(jnp.asarray(light, jnp.float64), jnp.asarray(coefficients), self.srgb))


@dataclass
class EdgeReadings:
    """Each edge's reading through the fitted processing: parameters (x0, R^2, lo, hi, turn), the
    standard error of R^2 (the shared parameters held, widened by the edge's reduced chi-square
    where above 1), whether the edge was fitted, and d(R^2)/d(shared) (how the reading moves with
    the curve and mask)."""

    theta: np.ndarray
    rho_sigma: np.ndarray
    ok: np.ndarray
    rho_slope: np.ndarray


def _pack(profiles: list[tuple], starts: list[np.ndarray], encoding: str) -> dict[str, np.ndarray]:
    n = len(profiles)
    size = BLOCK * max(1, math.ceil(n / BLOCK))
    A = {k: np.zeros((size, BINS)) for k in ("D", "S", "U", "W")}
    A.update(NX=np.ones(size), NY=np.zeros(size), X=np.full(size, 8.0), P=np.tile([0.0, 1.0, 0.0, 1.0, 0.0], (size, 1)))
    for j, ((d, s, v, se, nrm), start) in enumerate(zip(profiles, starts)):
        d, s, v, se = (np.asarray(x, np.float64) for x in (d, s, v, se))
        keep = np.flatnonzero((np.abs(d) <= REACH_PX) & np.isfinite(v) & np.isfinite(se) & (se > 0))[:BINS]
        u, slope = encoded(v[keep], encoding)
        m = len(keep)
        A["D"][j, :m], A["S"][j, :m], A["U"][j, :m] = d[keep], s[keep], u
        A["W"][j, :m] = 1.0 / (se[keep] * slope)
        A["D"][j, m:] = d[keep][-1] if m else 0.0
        A["NX"][j], A["NY"][j] = nrm
        A["X"][j] = float(np.max(np.abs(d[keep]))) + 1.0 if m else 8.0
        A["P"][j] = start
    return A


def _starts(profiles: list[tuple], radii: list[float]) -> list[np.ndarray]:
    out = []
    for (d, _s, v, _se, _n), r in zip(profiles, radii):
        d = np.asarray(d, np.float64)
        v = np.asarray(v, np.float64)
        lo, hi = np.mean(v[d < d.min() / 2]), np.mean(v[d > d.max() / 2])
        out.append(np.array([0.0, r * r, lo, hi, 0.0]))
    return out


def _normal_equations(A, P, g, terms, srgb):
    parts = [np.asarray(x) for x in _evaluate(P, g, A["X"], A["D"], A["S"], A["U"], A["W"], A["NX"], A["NY"],
                                                terms=terms, srgb=srgb)]
    r, Jp, Jg = parts
    return (r, np.einsum("nij,nik->njk", Jp, Jp), np.einsum("nij,nik->njk", Jp, Jg),
            np.einsum("nij,nik->jk", Jg, Jg), np.einsum("nij,ni->nj", Jp, r), np.einsum("nij,ni->j", Jg, r))


def _priors(terms: int) -> tuple[np.ndarray, np.ndarray]:
    """The shared parameters' prior residuals' centre and 1 sigma."""
    centre = np.zeros(terms + 2)
    centre[terms + 1] = math.log(SIGMA_PRIOR_PX)
    width = np.array([WARP_PRIOR] * terms + [AMOUNT_PRIOR, LOG_SIGMA_PRIOR])
    return centre, width


def _damped(M: np.ndarray, lam: float) -> np.ndarray:
    diag = np.einsum("...jj->...j", M)
    floor = 1e-9 * np.max(diag, axis=-1, keepdims=True) + 1e-300
    return M + lam * (np.eye(M.shape[-1]) * np.maximum(diag, floor)[..., None, :])


def solve(A: dict[str, np.ndarray], terms: int, srgb: bool, shared: bool = True,
          g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """Levenberg-Marquardt on the edges of ``A`` (:func:`_pack`), the shared parameters solved
    for (``shared``) or held at ``g``. Returns the edges' parameters, the shared ones, the cost
    (with the priors) and whether it converged."""
    P = A["P"].copy()
    centre, width = _priors(terms)
    g = centre.copy() if g is None else np.asarray(g, np.float64).copy()
    args = (A["X"], A["D"], A["S"], A["U"], A["W"], A["NX"], A["NY"])

    def cost(P, g):
        return float(np.sum(np.asarray(_cost(P, g, *args, terms=terms, srgb=srgb)))
                     + (np.sum(((g - centre) / width) ** 2) if shared else 0.0))

    lam, now, converged = 1e-3, cost(P, g), False
    for _ in range(MAX_STEPS):
        r, Ap, B, C, bp, bg = _normal_equations(A, P, g, terms, srgb)
        C = C + np.diag(1.0 / width**2)
        bg = bg + (g - centre) / width**2  # (the priors' gradient, in the sign of J^T r)
        while True:
            Ai = np.linalg.inv(_damped(Ap, lam))
            if shared:
                schur = _damped(C, lam) - np.einsum("nji,njk,nkl->il", B, Ai, B)
                dg = np.linalg.solve(schur, bg - np.einsum("nji,njk,nk->i", B, Ai, bp))
            else:
                dg = np.zeros_like(g)
            dp = np.einsum("njk,nk->nj", Ai, bp - np.einsum("njk,k->nj", B, dg))
            trial = cost(P - dp, g - dg)
            if math.isfinite(trial) and trial <= now:
                gain = now - trial
                P, g, now, lam = P - dp, g - dg, trial, max(lam / 3.0, 1e-9)
                break
            lam *= 10.0
            if lam > 1e10:
                return P, g, now, True  # no step lowers the cost: at its minimum to rounding
        if gain <= 1e-9 * now + 1e-9:
            converged = True
            break
    return P, g, now, converged


def _ridged_inverse(M: np.ndarray) -> np.ndarray:
    """Each 5 x 5 block's inverse with a ridge of 1e-10 of each parameter's own curvature (as
    ``lensfit.fitting.lm.covariance``): a direction the edge does not determine gets a huge
    variance, not none; blocks of padding (no curvature) invert to zero."""
    diag = np.einsum("njj->nj", M)
    empty = ~np.any(diag > 0, axis=1)
    ridge = np.eye(M.shape[-1]) * (1e-10 * np.maximum(diag, 1e-300))[:, None, :]
    out = np.linalg.inv(M + ridge + np.eye(M.shape[-1]) * empty[:, None, None])
    out[empty] = 0.0
    return out


def fit(profiles: list[tuple], radii: list[float], encoding: str, terms: int) -> tuple[ToneFit, EdgeReadings]:
    """The processing of ``profiles`` (the edge estimator's, ``(d, s, values, standard errors,
    normal)``, values linear as decoded by ``encoding``) with a tone curve of ``terms`` sine
    terms, and every edge read through it. ``radii``: each edge's first-pass radius (px), the
    start. The curve and mask are fitted on at most ``JOINT_EDGES`` edges spread over the stack,
    then every edge is read with them held. Edges whose radius is not finite are not read
    (``ok`` False)."""
    srgb = encoding == "srgb"
    use = [j for j, r in enumerate(radii) if r is not None and math.isfinite(r) and len(profiles[j][0]) >= 16]
    A = _pack([profiles[j] for j in use], _starts([profiles[j] for j in use], [radii[j] for j in use]), encoding)
    n = len(use)
    joint = np.unique(np.linspace(0, n - 1, min(n, JOINT_EDGES)).round().astype(int)) if n else np.zeros(0, int)
    with jax.enable_x64(True):
        # each edge alone through the declared encoding first, then the curve and mask with the
        # joint edges, then every edge with them held
        A["P"], _, _, _ = solve(A, terms, srgb, shared=False)
        J = _pack([profiles[use[k]] for k in joint], [A["P"][k] for k in joint], encoding)
        PJ, g, _, _ = solve(J, terms, srgb)
        rj = _normal_equations(J, PJ, g, terms, srgb)
        A["P"][joint] = PJ[:len(joint)]
        P, _, _, _ = solve(A, terms, srgb, shared=False, g=g)
        r, Ap, B, _, _, _ = _normal_equations(A, P, g, terms, srgb)
    _, width = _priors(terms)
    rJ, ApJ, BJ, CJ = rj[:4]
    schur = CJ + np.diag(1.0 / width**2) - np.einsum("nji,njk,nkl->il", BJ, _ridged_inverse(ApJ), BJ)
    bins_joint = int(np.sum(J["W"] > 0))
    chi2 = float(np.sum(rJ[:len(joint)] ** 2)) / max(bins_joint - 5 * len(joint) - len(g), 1)
    shared_cov = np.linalg.inv(schur) * max(chi2, 1.0)
    Ai = _ridged_inverse(Ap)
    bins_each = np.sum(A["W"] > 0, axis=1)
    edge_chi2 = np.sum(r * r, axis=1) / np.maximum(bins_each - 5, 1)
    theta = np.full((len(profiles), 5), np.nan)
    rho_sigma = np.full(len(profiles), np.nan)
    slope = np.full((len(profiles), len(g)), np.nan)
    ok = np.zeros(len(profiles), bool)
    dP = -np.einsum("njk,nkl->njl", Ai, B)  # how each edge's parameters follow the shared ones
    for k, j in enumerate(use):
        theta[j] = P[k]
        rho_sigma[j] = math.sqrt(max(Ai[k, 1, 1], 0.0) * max(edge_chi2[k], 1.0))
        slope[j] = dP[k, 1]
        ok[j] = bool(np.all(np.isfinite(P[k])) and bins_each[k] > 5)
    return ToneFit(terms, g, shared_cov, chi2, len(joint), srgb), EdgeReadings(theta, rho_sigma, ok, slope)
