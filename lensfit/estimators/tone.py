"""A developed image's processing fitted from a stack's own edges: the tone curve and the
sharpening a raw developer or a camera's JPEG engine applied, forward-modelled in the edge fit
(``lensfit.measurement.processing`` decides where it is needed and whether its readings are
kept).

In linear light a lens draws an edge as ``lo + (hi - lo) E(x; R)``, ``E`` the pixel-integrated
disk edge (``lensfit.measurement.psf``). A developer maps light through a monotone tone curve
and sharpens the result; the file holds::

    u(x) = S[ T(A * (lo + (hi - lo) E(x - x0; R))) ]

- ``T`` is the declared encoding (sRGB or none) warped by ``W(v) = v + sum_k c_k sin(k pi v)``
  on its [0, 1] scale, one curve for the whole stack (its first ``terms`` sine terms);
- ``S`` is an unsharp mask on the encoded values, ``u + a (u - g_sigma * u)``, ``g_sigma`` a
  Gaussian, one amount ``a`` and radius ``sigma`` for the stack (a negative amount is a blur);
- ``A`` is the lens's Airy pattern in linear light (its exact line-spread transform, the
  diffraction MTF of a circular pupil), where the caller gives each edge's ``lambda N`` in
  pixels: stopped down on small pixels it is as wide as the defocus of the sharpest edges.

Every edge has its own position, squared radius, levels and turn (as the edge estimator's
uniform disk); the curve and the mask are shared. What pins them apart from the blur: a tone
curve relabels the levels of an edge but cannot move where its profile starts and stops
changing, which is the disk's diameter (a disk's edge has a compact support), and one curve
must serve edges of every blur at once; halos beside the edges are the mask's. The joint
least-squares problem (thousands of residuals, a few per edge, a handful shared) is solved by
variable projection: Levenberg-Marquardt in the shared parameters alone, every edge solved to
its own optimum at each trial (the batched solver of ``lensfit.fitting.lm``), the step from the
normal equations reduced to the shared parameters (the Schur complement of the edges' blocks).
A joint step over edges and shared parameters together stalls where a few edges sit at a zero
blur; the projected cost has no such corners. The mask's amount and radius start from the best
of a few candidates (sharpening from none to strong), as the cost has a false minimum at a weak,
wide mask where a strong, narrow one was applied. The shared parameters' covariance, and how
each edge's radius moves with them, are returned so that their uncertainty reaches the f-number.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from lensfit.measurement.diffraction import circular_mtf
from lensfit.measurement.psf import pixel_edge_profile

#: The grid the mask's blurred copy (and the Airy pattern) is computed on, per edge: this many
#: points over the profile's reach and ``GRID_MARGIN_SIGMA`` sigmas beyond it, read at the bins by
#: cubic convolution (linear interpolation of an edge a pixel wide errs by a percent of its
#: contrast on this grid, the cubic by 0.03-0.1 %).
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
#: Each edge's parameters: position, squared radius, levels, turn and a ramp across the window
#: (which the Airy tails of neighbouring edges ask for, held near 0 by its prior: 1 sigma per px
#: as a share of the edge's contrast, as the edge estimator's).
PARAMS = 6
RAMP_PRIOR = 2e-3
#: The shared parameters' steps: at most this many; converged when a lightly damped step gains
#: less than ``GAIN_TOL`` in chi-square (residuals in standard errors). Each edge alone stops at
#: ``EDGE_FTOL`` (its chi-square), well below ``GAIN_TOL`` summed over the joint edges.
MAX_STEPS = 40
GAIN_TOL = 0.05
EDGE_FTOL = 1e-4
EDGE_STEPS = 60
#: A blur's squared radius (px^2) an edge starts from at least: below 0 its profile no longer
#: depends on it, and a reading that went there would stay.
RHO_FLOOR = 0.01
#: Where the mask starts: each of these (amount, sigma px) is tried on ``START_EDGES`` of the
#: joint edges, the curve held at the declared encoding, and the best kept.
MASK_STARTS = ((0.0, 1.0), (0.5, 0.7), (0.5, 1.0), (0.5, 1.5), (1.0, 0.7), (1.0, 1.0), (1.0, 1.5))
START_EDGES = 32
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


def _cubic(x, grid, y):
    """``y`` on the uniform ``grid`` at ``x`` by Keys' cubic convolution (a = -1/2)."""
    t = (x - grid[0]) / (grid[1] - grid[0])
    i = jnp.clip(jnp.floor(t).astype(jnp.int32), 1, grid.shape[0] - 3)
    u = jnp.clip(t - i.astype(t.dtype), 0.0, 1.0)
    v = 1.0 - u
    w1 = (1.5 * u - 2.5) * u * u + 1.0
    w2 = (1.5 * v - 2.5) * v * v + 1.0
    w0 = ((-0.5 * (u + 1.0) + 2.5) * (u + 1.0) - 4.0) * (u + 1.0) + 2.0
    w3 = 1.0 - w0 - w1 - w2
    return w0 * y[i - 1] + w1 * y[i] + w2 * y[i + 1] + w3 * y[i + 2]


def _edge_model(p, g, x_scale, d, s, nx, ny, airy, terms: int, srgb: bool, diffraction: bool):
    # p = (x0, rho = R^2, lo, hi, turn, ramp): the edge estimator's uniform disk and a ramp;
    # g = (c_1..c_terms, amount, log sigma); x_scale: the half-width of the edge's grid (px);
    # airy: the edge's lambda N in pixels, convolved in linear light where ``diffraction``.
    x0, rho, lo, hi, turn, ramp = (p[i] for i in range(PARAMS))
    c, amount, sigma = g[:terms], g[terms], jnp.exp(g[terms + 1])
    R = jnp.sqrt(0.5 * (rho + jnp.sqrt(rho * rho + 1e-12)) + 1e-12)
    x = d - x0 - turn * s
    # The Gaussian by FFT over a grid that reaches GRID_MARGIN_SIGMA sigmas beyond the bins: the
    # transform wraps one flat end onto the other only within that margin, off the bins. (The
    # grid is not a parameter: its reach follows sigma without a derivative, which would otherwise
    # reach the MTF's square root at its cut-off.)
    reach = x_scale + GRID_MARGIN_SIGMA * jax.lax.stop_gradient(sigma)
    grid = jnp.linspace(-reach, reach, GRID_POINTS, endpoint=False)
    frequency = jnp.fft.rfftfreq(GRID_POINTS, d=grid[1] - grid[0])
    light = lo + (hi - lo) * pixel_edge_profile(grid, R, nx, ny)
    if diffraction:
        # The Airy pattern on the profile's steps (zero at both ends, so the transform does not
        # wrap the edge onto itself), summed back.
        steps = jnp.diff(light, prepend=light[:1])
        spectrum = jnp.fft.rfft(steps)
        mtf = circular_mtf(frequency * airy).astype(spectrum.dtype)
        light = light[0] + jnp.cumsum(jnp.fft.irfft(spectrum * mtf, n=GRID_POINTS))
        here = tone_curve(_cubic(x, grid, light) + ramp * x, c, srgb)
    else:
        here = tone_curve(lo + (hi - lo) * pixel_edge_profile(x, R, nx, ny) + ramp * x, c, srgb)
    spectrum = jnp.fft.rfft(tone_curve(light + ramp * grid, c, srgb))
    gauss = jnp.exp(-2.0 * (jnp.pi * sigma * frequency) ** 2).astype(spectrum.dtype)
    blurred = jnp.fft.irfft(spectrum * gauss, n=GRID_POINTS)
    return here + amount * (here - _cubic(x, grid, blurred))


def _residuals(p, g, x_scale, d, s, u, w, nx, ny, airy, terms: int, srgb: bool, diffraction: bool):
    r = w * (u - _edge_model(p, g, x_scale, d, s, nx, ny, airy, terms, srgb, diffraction))
    present = (jnp.max(w) > 0).astype(r.dtype)  # (an edge of padding has no prior either)
    return jnp.concatenate([r, (present * p[5] / (RAMP_PRIOR * jnp.abs(p[3] - p[2]) + 1e-12))[None]])


_AXES = (0, None, 0, 0, 0, 0, 0, 0, 0, 0)
_DATA = ("X", "D", "S", "U", "W", "NX", "NY", "AIRY")
_STATIC = ("terms", "srgb", "diffraction")


@partial(jax.jit, static_argnames=_STATIC)
def _evaluate(P, g, *data, terms: int, srgb: bool, diffraction: bool):
    """Residuals, their Jacobian in each edge's parameters and in the shared ones, for a block."""
    fn = partial(_residuals, terms=terms, srgb=srgb, diffraction=diffraction)
    r = jax.vmap(fn, _AXES)(P, g, *data)
    Jp = jax.vmap(jax.jacfwd(fn, 0), _AXES)(P, g, *data)
    Jg = jax.vmap(jax.jacfwd(fn, 1), _AXES)(P, g, *data)
    return r, Jp, Jg


@partial(jax.jit, static_argnames=_STATIC)
def _edges_alone(P, g, *data, terms: int, srgb: bool, diffraction: bool):
    """Every edge of a block solved alone, the shared parameters held at ``g``: parameters and
    cost per edge."""
    from lensfit.fitting.lm import least_squares

    def one(p, *row):
        def fn(q, args):
            return _residuals(q, g, *args, terms=terms, srgb=srgb, diffraction=diffraction)
        theta, cost, _ = least_squares(fn, p, row, max_steps=EDGE_STEPS, ftol=EDGE_FTOL, rtol=1e-7)
        return theta, cost
    return jax.vmap(one)(P, *data)


@dataclass
class ToneFit:
    """The processing fitted to a stack's edges.

    Attributes
    ----------
    terms : the tone curve's sine terms
    shared : (c_1..c_terms, mask amount, log mask sigma)
    shared_cov : their covariance (widened by the reduced chi-square where above 1)
    chi2_reduced : the joint fit's reduced chi-square
    misfit : how far the model misses the joint edges' profiles beyond their noise, RMS, as a
        share of each edge's contrast (a reduced chi-square grows with the images' signal to
        noise for one same small misfit; this does not)
    edges : the edges it rests on
    srgb : whether the curve is a warp of the sRGB encoding (else of the identity)
    """

    terms: int
    shared: np.ndarray
    shared_cov: np.ndarray
    chi2_reduced: float
    misfit: float
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
    """Each edge's reading through the fitted processing: parameters (x0, R^2, lo, hi, turn, ramp), the
    standard error of R^2 (the shared parameters held, widened by the edge's reduced chi-square
    where above 1), whether the edge was fitted, and d(R^2)/d(shared) (how the reading moves with
    the curve and mask)."""

    theta: np.ndarray
    rho_sigma: np.ndarray
    ok: np.ndarray
    rho_slope: np.ndarray


def _pack(profiles: list[tuple], starts: list[np.ndarray], encoding: str,
          airy: list[float] | None) -> dict[str, np.ndarray]:
    n = len(profiles)
    size = BLOCK * max(1, math.ceil(n / BLOCK))
    A = {k: np.zeros((size, BINS)) for k in ("D", "S", "U", "W")}
    A.update(NX=np.ones(size), NY=np.zeros(size), X=np.full(size, 8.0), AIRY=np.zeros(size),
             P=np.tile([0.0, 1.0, 0.0, 1.0, 0.0, 0.0], (size, 1)), diffraction=airy is not None)
    if airy is not None:
        A["AIRY"][:n] = airy
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


def _pack_rows(rows: list[int], profiles: list[tuple], radii: list[float], encoding: str,
               airy_px: list[float] | None) -> dict[str, np.ndarray]:
    """:func:`_pack` of the edges ``rows`` of ``profiles``, each starting from its radius."""
    chosen = [profiles[j] for j in rows]
    return _pack(chosen, _starts(chosen, [radii[j] for j in rows]), encoding,
                 None if airy_px is None else [airy_px[j] for j in rows])


def _starts(profiles: list[tuple], radii: list[float]) -> list[np.ndarray]:
    out = []
    for (d, _s, v, _se, _n), r in zip(profiles, radii):
        d = np.asarray(d, np.float64)
        v = np.asarray(v, np.float64)
        lo, hi = np.mean(v[d < d.min() / 2]), np.mean(v[d > d.max() / 2])
        out.append(np.array([0.0, r * r, lo, hi, 0.0, 0.0]))
    return out


def _normal_equations(A, P, g, terms, srgb):
    parts = [np.asarray(x) for x in _evaluate(P, g, *(A[k] for k in _DATA), terms=terms, srgb=srgb,
                                                diffraction=A["diffraction"])]
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


def solve_edges(A: dict[str, np.ndarray], terms: int, srgb: bool, g: np.ndarray) -> tuple[np.ndarray, float]:
    """Every edge of ``A`` (:func:`_pack`) at its own optimum with the shared parameters held at
    ``g``, from ``A["P"]``: the parameters and the summed cost."""
    start = A["P"].copy()
    start[:, 1] = np.maximum(start[:, 1], RHO_FLOOR)
    P, cost = [], 0.0
    for b in range(0, start.shape[0], BLOCK):
        part = slice(b, b + BLOCK)
        p, c = _edges_alone(start[part], g, *(A[k][part] for k in _DATA), terms=terms, srgb=srgb,
                            diffraction=A["diffraction"])
        P.append(np.asarray(p))
        cost += float(np.sum(np.asarray(c)))
    return np.concatenate(P), cost


def solve(A: dict[str, np.ndarray], terms: int, srgb: bool, g: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """The shared parameters from ``g``, by Levenberg-Marquardt on the projected cost (see the
    module notes). Returns the edges' parameters, the shared ones, the cost (with the priors) and
    whether it converged."""
    centre, width = _priors(terms)
    g = np.asarray(g, np.float64).copy()
    P, cost = solve_edges(A, terms, srgb, g)
    now, lam = cost + float(np.sum(((g - centre) / width) ** 2)), 1e-3
    for _ in range(MAX_STEPS):
        _, Ap, B, C, bp, bg = _normal_equations(A, P, g, terms, srgb)
        Ai = _ridged_inverse(Ap)
        schur = C + np.diag(1.0 / width**2) - np.einsum("nji,njk,nkl->il", B, Ai, B)
        gradient = bg + (g - centre) / width**2 - np.einsum("nji,njk,nk->i", B, Ai, bp)
        while True:
            trial_g = g - np.linalg.solve(_damped(schur, lam), gradient)
            trial_P, cost = solve_edges(dict(A, P=P), terms, srgb, trial_g)
            trial = cost + float(np.sum(((trial_g - centre) / width) ** 2))
            if math.isfinite(trial) and trial <= now:
                gain = now - trial
                P, g, now, lam = trial_P, trial_g, trial, max(lam / 3.0, 1e-9)
                break
            lam *= 10.0
            if lam > 1e8:
                return P, g, now, True  # no step lowers the cost: at its minimum to the edges' tolerance
        if gain <= GAIN_TOL and lam <= 1.0:
            return P, g, now, True
    return P, g, now, False


def _mask_start(A: dict[str, np.ndarray], terms: int, srgb: bool) -> np.ndarray:
    """The shared parameters to start from: the declared encoding and the best of ``MASK_STARTS``
    on ``START_EDGES`` of the edges of ``A``."""
    n = int(np.sum(np.any(A["W"] > 0, axis=1)))
    if n == 0:
        return _priors(terms)[0]
    pick = np.unique(np.linspace(0, n - 1, min(n, START_EDGES)).round().astype(int))
    rows = np.concatenate([pick, np.full(BLOCK - len(pick) % BLOCK if len(pick) % BLOCK else 0, pick[0])])
    few = {k: (v[rows] if isinstance(v, np.ndarray) else v) for k, v in A.items()}
    few["W"][len(pick):] = 0.0  # (padding to the compiled block: edges of no weight)
    best = None
    for amount, sigma in MASK_STARTS:
        g = _priors(terms)[0]
        g[terms], g[terms + 1] = amount, math.log(sigma)
        cost = solve_edges(few, terms, srgb, g)[1]
        if best is None or cost < best[0]:
            best = (cost, g)
    return best[1]


def _ridged_inverse(M: np.ndarray) -> np.ndarray:
    """Each edge's block's inverse with a ridge of 1e-10 of each parameter's own curvature (as
    ``lensfit.fitting.lm.covariance``): a direction the edge does not determine gets a huge
    variance, not none; blocks of padding (no curvature) invert to zero."""
    diag = np.einsum("njj->nj", M)
    empty = ~np.any(diag > 0, axis=1)
    ridge = np.eye(M.shape[-1]) * (1e-10 * np.maximum(diag, 1e-300))[:, None, :]
    out = np.linalg.inv(M + ridge + np.eye(M.shape[-1]) * empty[:, None, None])
    out[empty] = 0.0
    return out


def _usable(profiles: list[tuple], radii: list[float]) -> list[int]:
    return [j for j, r in enumerate(radii) if r is not None and math.isfinite(r) and len(profiles[j][0]) >= 16]


def fit(profiles: list[tuple], radii: list[float], encoding: str, terms: int,
        airy_px: list[float] | None = None) -> tuple[ToneFit, EdgeReadings]:
    """The processing of ``profiles`` (the edge estimator's, ``(d, s, values, standard errors,
    normal)``, values linear as decoded by ``encoding``) with a tone curve of ``terms`` sine
    terms, and every edge read through it (:func:`read`). ``radii``: each edge's first-pass
    radius (px), the start; ``airy_px``: each edge's lambda N in pixels, where the Airy pattern is
    modelled. The curve and mask are fitted on at most ``JOINT_EDGES`` edges spread over the
    stack, each edge first read alone through the declared encoding."""
    srgb = encoding == "srgb"
    use = _usable(profiles, radii)
    joint = [use[k] for k in np.unique(np.linspace(0, len(use) - 1, min(len(use), JOINT_EDGES)).round().astype(int))]
    J = _pack_rows(joint, profiles, radii, encoding, airy_px)
    with jax.enable_x64(True):
        J["P"], _ = solve_edges(J, terms, srgb, _priors(terms)[0])
        PJ, g, _, _ = solve(J, terms, srgb, _mask_start(J, terms, srgb))
        r, ApJ, BJ, CJ, _, _ = _normal_equations(J, PJ, g, terms, srgb)
    _, width = _priors(terms)
    schur = CJ + np.diag(1.0 / width**2) - np.einsum("nji,njk,nkl->il", BJ, _ridged_inverse(ApJ), BJ)
    bins_joint = int(np.sum(J["W"] > 0))
    chi2 = float(np.sum(r[:len(joint), :BINS] ** 2)) / max(bins_joint - PARAMS * len(joint) - len(g), 1)
    weight = J["W"][:len(joint)]
    present = weight > 0
    bins = np.maximum(np.sum(present, axis=1), 1)
    excess = np.maximum(np.sum(r[:len(joint), :BINS] ** 2 * present, axis=1) / bins - 1.0, 0.0)
    noise = np.sum(np.where(present, 1.0 / np.where(present, weight, 1.0) ** 2, 0.0), axis=1) / bins
    contrast = np.maximum(np.abs(PJ[:len(joint), 3] - PJ[:len(joint), 2]), 1e-6)
    misfit = float(np.sqrt(np.median(excess * noise / contrast**2))) if len(joint) else math.nan
    fitted = ToneFit(terms, g, np.linalg.inv(schur) * max(chi2, 1.0), chi2, misfit, len(joint), srgb)
    return fitted, read(fitted, profiles, radii, encoding, airy_px)


def read(fitted: ToneFit, profiles: list[tuple], radii: list[float], encoding: str,
         airy_px: list[float] | None = None) -> EdgeReadings:
    """Every edge of ``profiles`` read with the curve and mask of ``fitted`` held (``radii`` the
    starts, ``airy_px`` as :func:`fit`'s). Edges whose radius is not finite are not read (``ok``
    False)."""
    use = _usable(profiles, radii)
    A = _pack_rows(use, profiles, radii, encoding, airy_px)
    g = fitted.shared
    with jax.enable_x64(True):
        P, _ = solve_edges(A, fitted.terms, fitted.srgb, g)
        r, Ap, B, _, _, _ = _normal_equations(A, P, g, fitted.terms, fitted.srgb)
    Ai = _ridged_inverse(Ap)
    bins_each = np.sum(A["W"] > 0, axis=1)
    edge_chi2 = np.sum(r[:, :BINS] ** 2, axis=1) / np.maximum(bins_each - PARAMS, 1)
    theta = np.full((len(profiles), PARAMS), np.nan)
    rho_sigma = np.full(len(profiles), np.nan)
    slope = np.full((len(profiles), len(g)), np.nan)
    ok = np.zeros(len(profiles), bool)
    dP = -np.einsum("njk,nkl->njl", Ai, B)  # how each edge's parameters follow the shared ones
    for k, j in enumerate(use):
        theta[j] = P[k]
        rho_sigma[j] = math.sqrt(max(Ai[k, 1, 1], 0.0) * max(edge_chi2[k], 1.0))
        slope[j] = dP[k, 1]
        ok[j] = bool(np.all(np.isfinite(P[k])) and bins_each[k] > 5)
    return EdgeReadings(theta, rho_sigma, ok, slope)
