"""The edge estimator's batched fits (``lensfit.estimators.edge`` describes the method): every
edge profile of a stack solved by Levenberg-Marquardt (``lensfit.fitting.lm``) under ``jax.vmap``, in
chunks of a fixed size padded to one of a few profile sizes, so that a few compiled shapes per
kind of fit (uniform disk, two disks, with the Airy pattern) serve any stack; compiled once
per installation (``lensfit.runtime.jaxcache``) and loaded in the background (:func:`prewarm`). The model,
its residuals and start grids are in ``lensfit.estimators.edge_model``."""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from lensfit.runtime import jaxcache
from lensfit.measurement.diffraction import edge_kernel
from lensfit.estimators.edge_model import (AIRY_START_SHARES, Profile, chunks, from_moment, grid_start,
                                           moment_residuals, residuals, shape_start, squared_radius, to_moment)
from lensfit.estimators.profile import NBINS_ACROSS, STRIPS

#: Edges per compiled call, bins per edge profile (at most; STRIPS x NBINS_ACROSS) and the
#: solver's step limit: fixed, so that one compilation serves every stack.
CHUNK = 16
MAX_STEPS = 40
#: Problems per compiled call of the costlier fits, two disks and the Airy pattern: every lane of a
#: chunk runs until its slowest problem stops, and two disks take 3-40 steps (median 11-15). Four
#: took the shaped fit of the demo enlarged 1.25x (217 edges) from 0.24-0.33 s to 0.19-0.20 s warm
#: (2 and 8: no faster than 4), and the Airy pass's wait for its last chunks from 0.64-0.81 s to
#: 0.37-0.41 s on two stacks (whole rounds about 3 % faster); the uniform disk's first passes are
#: fastest in 16 (4: 0.49-0.60 s, 16: 0.46-0.48 s for the demo's measure stage). The readings
#: agree to rounding (a problem may land in the other profile size: 1e-14 in a sigma, and after
#: the diffraction rounds, which amplify it, 1e-9 in f and N).
SMALL_CHUNK = 4
#: The modules whose source defines the compiled fit (a change traces it afresh; lensfit.runtime.jaxcache).
AOT_MODULES = ("lensfit.estimators.edge_fit", "lensfit.estimators.edge_model", "lensfit.measurement.psf",  # (the
               "lensfit.fitting.lm", "lensfit.measurement.diffraction", "lensfit.optics.checks")  # profile is data)
#: The solver stops when a step gains less than this in chi-square (parameters within 1e-3
#: standard errors of the minimum).
FTOL = 1e-6
#: The chi-square cost of a blur of this diameter, the rest held, is returned with each fit
#: (``lensfit.estimators.edge`` tests sub-pixel readings by it).
PROBE_C_PX = 1.0
NPIX = STRIPS * NBINS_ACROSS
#: Bins per profile the compiled fits take (a problem goes to the smallest that holds it): on the
#: demo stack 70 % of the second pass's profiles have 64 bins or fewer. Two sizes took the warm
#: measure stage from 0.75 to 0.48-0.61 s; a third (128) saved little more and cost its loading
#: in every new process.
NPIX_CLASSES = (64, NPIX)


def _fit_batch(d, s, v, w, nx, ny, theta_disk, airy, shaped: bool, diffraction: bool = False, warm: bool = False):
    # airy: per problem the Airy kernel (knots, slope changes, tail); dummies without diffraction
    from lensfit.fitting import lm

    def one(d, s, v, w, nx, ny, theta_disk, airy):
        args = Profile(d, s, v, w, nx, ny, airy if diffraction else None)
        fn = partial(residuals, shaped=shaped)
        # The uniform disk starts from a grid over the radius; two disks (which have more than one
        # local minimum: a core in a halo, a bright rim) from the best of a grid of shapes at the
        # disk's solution.
        # With the Airy pattern, whose blur the uniform disk read as its own (a disk reading is
        # never smaller), the radius lies between 0 and the disk's: a grid of 8 radii over that
        # interval, where the full grid's 24 were most of the solve's cost with the pattern.
        if shaped:
            start = shape_start(theta_disk, args)
        elif diffraction and warm:  # from the solution at a nearby Airy scale (an earlier round), its ramp 0
            start = jnp.concatenate([theta_disk, jnp.zeros(1)])
        elif diffraction:
            radius = jnp.sqrt(squared_radius(theta_disk[1]))
            start = jnp.concatenate([grid_start(d, s, v, w, nx, ny, airy, radius * jnp.asarray(AIRY_START_SHARES)),
                                     jnp.zeros(1)])  # the ramp
        else:
            start = grid_start(d, s, v, w, nx, ny)
        # Two disks are solved with their second moment as a parameter (edge_model.moment_residuals).
        solve_fn, solve_start = (moment_residuals, to_moment(start)) if shaped else (fn, start)
        theta, cost, converged = lm.least_squares(solve_fn, solve_start, args, max_steps=MAX_STEPS, rtol=1e-8,
                                                  atol=1e-10, ftol=FTOL)
        if shaped:
            theta = from_moment(theta)
        # A uniform disk that has not converged is a failed reading; two disks (slow to settle in
        # their shape, which moves c little) keep their best point, which the covariance and
        # chi-square describe.
        ok = jnp.isfinite(cost) & jnp.all(jnp.isfinite(theta)) & (converged | shaped)
        r, J = lm.residuals_and_jacobian(fn, theta, args)
        r = r[:d.shape[0]]  # the blur's rows, without the shape's priors
        n_eff = jnp.sum(w > 0).astype(w.dtype)  # bins
        # Residuals are in units of each bin's own standard error; a reduced chi-square above 1
        # (model misfit) inflates the covariance, one below 1 does not shrink it.
        dof = jnp.maximum(n_eff - theta.shape[0], 1.0)
        s2 = jnp.sum(r * r) / dof
        cov = jnp.maximum(s2, 1.0) * lm.covariance(J)
        # How much worse a 1 px blur fits (the rest held): what a sub-pixel reading is worth.
        probe = jnp.sum(fn(theta.at[1].set(PROBE_C_PX**2 / 4.0), args) ** 2) - cost
        if not shaped:  # the same layout as the shaped fit's: a = 0, u = 0, no covariance
            k = 7 - theta.shape[0]  # (the ramp of a diffraction fit takes a's place: not shaped)
            theta = jnp.concatenate([theta, jnp.zeros(k)])
            cov = jnp.pad(cov, ((0, k), (0, k)))
        return theta, cov, jnp.sqrt(s2), ok, probe

    return jax.vmap(one)(d, s, v, w, nx, ny, theta_disk, airy)


class FitQueue:
    """The batched fits of one kind (``shaped``, ``diffraction``) for problems that arrive one at a
    time (:meth:`add`): each profile size's chunk is dispatched as soon as it is full, so that
    JAX solves it while the caller gathers the next profiles, and the rest at :meth:`results`,
    which moves every result to the host at once. The chunks are those of one call with every
    problem (the same padding, so the same readings).

    Every problem is padded to the smallest of ``NPIX_CLASSES`` that holds its bins and each
    class to whole chunks of ``CHUNK`` (``SMALL_CHUNK`` for two disks and the Airy pattern): a few
    compiled shapes per kind of fit for any stack."""

    def __init__(self, shaped: bool, diffraction: bool, warm: bool = False):
        self.static = {"shaped": shaped, "diffraction": diffraction}
        if warm:  # (only then in the key: the stored fits without it keep theirs)
            self.static["warm"] = True
        self.chunk = SMALL_CHUNK if shaped or diffraction else CHUNK
        self.items: list[tuple] = []  # (sample, disk, airy)
        self.classes: dict[int, list[int]] = {c: [] for c in NPIX_CLASSES}
        self.sent = dict.fromkeys(NPIX_CLASSES, 0)
        self.calls: list[tuple[list[int], list]] = []

    def add(self, sample: tuple, disk: np.ndarray | None = None, airy: float | None = None) -> None:
        if self.static["diffraction"] and (disk is None or airy is None):
            raise ValueError("a fit with the Airy pattern needs the item's uniform-disk solution and Airy scale")
        self.items.append((sample, disk, airy))
        npix = next((c for c in NPIX_CLASSES if len(sample[0]) <= c), NPIX)
        self.classes[npix].append(len(self.items) - 1)
        if len(self.classes[npix]) - self.sent[npix] == self.chunk:
            self._send(npix)

    def _send(self, npix: int) -> None:
        members = self.classes[npix][self.sent[npix]:]
        self.sent[npix] = len(self.classes[npix])
        if not members:
            return
        samples = [self.items[i][0] for i in members]
        disk = [self.items[i][1] for i in members] if self.static["shaped"] or self.static["diffraction"] else None
        airy = [self.items[i][2] for i in members] if self.static["diffraction"] else None
        with jax.enable_x64(True):  # numpy in: no eager JAX operation between the compiled calls
            self.calls.append((members, [jaxcache.call("edge-fit", _fit_batch, chunk, self.static, AOT_MODULES)
                                         for chunk in chunks(npix, self.chunk, samples, disk, airy)]))

    def results(self) -> list[tuple]:
        """theta, cov, rms, ok and the chi-square cost of a 1 px blur (``probe``) per problem, in
        the order added."""
        classes = self.classes
        # A class's last, partial chunk costs as much as a full one (every lane of a chunk runs
        # until its slowest problem stops): its problems move up a size where the next class's
        # padding holds them at no extra chunk (they are the ones not yet dispatched).
        for small, large in zip(NPIX_CLASSES, NPIX_CLASSES[1:]):
            rest = len(classes[small]) % self.chunk
            extra = math.ceil((len(classes[large]) + rest) / self.chunk) - math.ceil(len(classes[large]) / self.chunk)
            if rest and extra * large < small:
                classes[large] += classes[small][len(classes[small]) - rest:]
                del classes[small][len(classes[small]) - rest:]
        for npix in NPIX_CLASSES:
            self._send(npix)
        with jax.enable_x64(True):
            fetched = jax.device_get([parts for _, parts in self.calls])
        out: list = [None] * len(self.items)
        for (members, _), parts in zip(self.calls, fetched):
            theta, cov, rms, ok, probe = (np.concatenate([p[j] for p in parts]) for j in range(5))
            for k, i in enumerate(members):
                out[i] = (theta[k], cov[k], float(rms[k]), bool(ok[k]), float(probe[k]))
        return out


def fit_profiles(samples: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], shaped: bool = True,
                 disk: list[np.ndarray] | None = None, airy: list[float] | None = None, warm: bool = False):
    """Fit a list of (d, s, values, standard errors, normal); returns theta, cov, rms, ok and the
    chi-square cost of a 1 px blur (``probe``) per item (:class:`FitQueue`).
    The two-disk fit (``shaped``) and the fit with the Airy pattern start from each item's
    uniform-disk solution, ``disk``; ``airy``: each item's Airy scale in px (diffraction
    modelled; None: not); ``warm``: the fits with the pattern start at ``disk`` itself (a
    solution with the pattern at a nearby scale; its ramp at 0) instead of a grid over its radius."""
    if airy is not None and (disk is None or len(disk) != len(samples)):
        raise ValueError("a fit with the Airy pattern starts from each item's uniform-disk solution: give disk")
    queue = FitQueue(shaped, airy is not None, warm)
    for k, smp in enumerate(samples):
        queue.add(smp, None if disk is None else disk[k], None if airy is None else airy[k])
    return queue.results()


def _dummy(npix: int) -> list[tuple]:
    """One problem of ``npix`` bins with nothing to fit (zero weights: the solver stops at once)."""
    d = np.linspace(-4.0, 4.0, npix)
    return [(d, np.zeros_like(d), np.zeros_like(d), np.full_like(d, np.inf), (1.0, 0.0))]


_DISK = [np.array([0.0, 1.0, 0.0, 1.0, 0.0])]


def prewarm(shaped: bool = True, diffraction: bool = False) -> None:
    """Load (or trace and compile) the batched fits that ``lensfit.estimators.edge.measure_images``
    calls, for every profile size (``NPIX_CLASSES``), on chunks with nothing to fit, so that a
    caller can overlap the loading (about 0.1 s per kind and size from the stores, seconds without) with other
    work: ``lensfit.measurement.measure`` runs it in a background thread while it reads and detects."""
    # One size per call (a lone small problem would move up a size), in the order of use.
    for npix in NPIX_CLASSES:
        fit_profiles(_dummy(npix), False)  # the first pass (never with the Airy model)
    for npix in NPIX_CLASSES if shaped and not diffraction else ():
        fit_profiles(_dummy(npix), True, _DISK)
    if diffraction:
        prewarm_airy()


def prewarm_airy(rounds: bool = True) -> None:
    """Load the fits with the Airy pattern (every profile size) and compute its tables, as
    :func:`prewarm` does for the plain fits: ``lensfit.measurement.pipeline`` runs it in the background
    while the first fit runs, before its diffraction test. ``rounds=False``: not the fits that
    start from a round before (what the diffraction test alone calls; a round's own measuring
    loads them, :func:`prewarm`)."""
    edge_kernel(1.0, 1.0, 0.0)
    for npix in NPIX_CLASSES:
        fit_profiles(_dummy(npix), False, _DISK, airy=[1.0])
    for npix in NPIX_CLASSES if rounds else ():  # the later rounds', started from the round before
        fit_profiles(_dummy(npix), False, _DISK, airy=[1.0], warm=True)
