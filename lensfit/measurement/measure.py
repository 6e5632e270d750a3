"""From an image stack to samples of (distance from the lens, blur-disk diameter, uncertainty).

Pipeline: read the manifest -> detect every target in every image -> calibrate intrinsics per
lens setting (focal length in px; shared principal point and distortion) -> pose of each
target in each image -> the straight edges of each target, with the distance of their ends and
middle from the lens plane -> a blur estimator on each edge.

``measure(stack)`` returns a :class:`SampleTable`; the CLI writes it as CSV or JSON.
"""

from __future__ import annotations

import threading
import time
from functools import partial
from pathlib import Path
from typing import Any, Callable

import numpy as np

from lensfit.runtime.clock import StageClock
from lensfit.calibration.camera import estimate_pose, few_informative_views
from lensfit.errors import InputError, SpecError
from lensfit.measurement.views import calibrate_views
from lensfit.estimators import EdgeTask, get_estimator
from lensfit.estimators.base import Flag
from lensfit.runtime.parallel import check_jobs, in_threads
from lensfit.io.samples import Sample, SampleTable
from lensfit.io.stack import Stack, load_stack
from lensfit.measurement.edge_geometry import (bright_offset, edge_tasks, refined_detections, tone_shifts,
                                               undistorted_blur)
from lensfit.calibration.targets import Detection, Target, detection_copies

#: What of an edge task's context the edge estimator reads (the rest, the target's board and
#: pose for the ``target`` estimator, is not kept with the samples).
EDGE_CONTEXT = ("end_depths_mm",)
SATURATION_LEVEL = 0.995
SATURATED_FRACTION_LIMIT = 0.01


def _hold_bytes() -> int:
    """A quarter of the machine's memory, at most 4 GB (2 GB where the system does not say)."""
    import os

    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return 2 << 30
    return int(min(4 << 30, total // 4))


#: A stack whose images take at most this many bytes (float64) is held in memory between the
#: stages (decoded once: a 12-shot 24 MP stack, 2.3 GB, was decoded eight times over its passes
#: and diffraction rounds, 11 of its 35 s); of a larger one, the 16- and 8-bit grey images are
#: held as their files' integers in part of it (``lensfit.io.stack.COMPACT_HOLD_SHARE``), the
#: others (RAW files, colour) read again where needed, a few images in memory at once.
HOLD_BYTES = _hold_bytes()
#: Images searched for targets at once are bounded by memory as well as by ``jobs``: each holds
#: about this many bytes per pixel while it is searched (the float64 image, a float32 and three
#: 8-bit copies, the percentile's sort), and all of them at most ``IN_FLIGHT_BYTES`` (a 45 MP
#: camera: two at a time; 24 MP: five).
DETECT_BYTES_PER_PX = 24
IN_FLIGHT_BYTES = 3 << 30


def _check_saturation(stack: Stack, index: int, image: np.ndarray, det: Detection) -> None:
    pts = det.image_points_px
    x0, y0 = np.floor(pts.min(axis=0)).astype(int)
    x1, y1 = np.ceil(pts.max(axis=0)).astype(int)
    region = image[max(y0, 0):y1 + 1, max(x0, 0):x1 + 1]
    if region.size and np.mean(region >= SATURATION_LEVEL) > SATURATED_FRACTION_LIMIT:
        raise SpecError(stack.images[index].file, "", f"{100 * np.mean(region >= SATURATION_LEVEL):.1f}% of the "
                        f"pixels on target {det.target_id!r} are saturated; expose less (blur cannot be measured "
                        "on clipped edges)")


def _prewarm(estimator: str, diffraction: bool) -> threading.Thread | None:
    """Import JAX and load the edge estimator's compiled fits in a background thread while the
    images are read and the targets detected and calibrated (OpenCV and numpy release the
    interpreter, so the two overlap on two cores: of about 1.2 s of CPU, 0.4 s of a fresh
    process's wall time on the demo)."""
    if estimator not in ("edge", "edge-disk"):
        return None

    def load():
        from lensfit.estimators import edge_fit

        edge_fit.prewarm(shaped=estimator == "edge", diffraction=diffraction)
    return in_background(load, "lensfit-prewarm")


_LAST_LOADER: list[threading.Thread | None] = [None]


def in_background(load: Callable[[], None], name: str) -> threading.Thread:
    """Run ``load`` (loading compiled code ahead of its use) in a started thread, which the
    caller joins before the use. A failure there is left for the use itself to meet and report.
    The loaders run one after another, in the order they were started (each waits for the one
    before): the first needed is in soonest, and the measuring keeps the other core."""
    before = _LAST_LOADER[0]

    def work():
        if before is not None:
            before.join()
        try:
            load()
        except Exception:  # noqa: BLE001 - the same call in the measuring raises it properly
            pass

    thread = threading.Thread(target=work, name=name)
    _LAST_LOADER[0] = thread
    thread.start()
    return thread


def measure(stack: Stack | str | Path, estimator: str = "edge", *, refine: bool = True,
            progress: Callable[[str, int, int], None] | None = None,
            airy_px: dict[str, float] | None = None, jobs: int | None = None) -> SampleTable:
    """Measure blur versus distance on every target edge of a stack.

    Parameters
    ----------
    stack : Stack or str or Path
        A :class:`~lensfit.io.stack.Stack`, or the path of a stack folder.
    estimator : str
        A name from ``lensfit.estimators.ESTIMATORS``.
    refine : bool
        Refine the detected corners by intersecting the measured edge lines, then calibrate and
        solve the poses again (more precise intrinsics and distances).
    progress : callable, optional
        Called as ``progress(stage, done, total)``.
    airy_px : dict, optional
        Per setting label, the Airy pattern's scale ``lambda N_w / p`` in px: the edge estimators
        then model diffraction and read the defocus blur alone (flag ``diffraction_modelled``;
        ``lensfit.measurement.diffraction``, ``lensfit.measurement.pipeline``).
    jobs : int, optional
        Images read and searched for targets at once, in threads (default: the cores this
        process may use; ``lensfit.runtime.parallel``). The results are the same whatever it is.

    Returns
    -------
    SampleTable

    Raises
    ------
    lensfit.errors.SpecError, lensfit.errors.InputError
        Unreadable or inconsistent input, saturated targets, a setting that cannot be calibrated.

    Examples
    --------
    >>> from lensfit.measurement.measure import measure
    >>> table = measure("out/demo")                     # doctest: +SKIP
    >>> table.write("samples.csv")                      # doctest: +SKIP
    """
    return Measurement(stack, estimator, refine=refine, progress=progress, jobs=jobs).read(airy_px)


class Measurement:
    """A stack being measured, which can read its edges again on request.

    ``read()`` is :func:`measure`'s table; ``read(airy_px)`` after it reads the same targets
    again through each setting's Airy pattern (``lensfit.measurement.pipeline``'s diffraction
    rounds): the targets as first detected are taken instead of detecting them again, and the
    corners are refined, the intrinsics calibrated and the blur read afresh, from the first
    pass's edge profiles where they were kept (``keep_profiles``; about 4 kB an edge; the same
    readings, a quarter less time a round). ``reread`` reads a few edges of a table again with
    the pattern, not a new table. ``on_edges`` is called with the number of settings and of
    edges once the first read knows its edges, before they are measured (the pipeline starts
    loading the fit's compiled functions for them there, in the background). The other
    arguments are :func:`measure`'s.
    """

    def __init__(self, stack: Stack | str | Path, estimator: str = "edge", *, refine: bool = True,
                 progress: Callable[[str, int, int], None] | None = None, jobs: int | None = None,
                 keep_profiles: bool = False, on_edges: Callable[[int, int], None] | None = None):
        self.fn = get_estimator(estimator)
        self.jobs = check_jobs(jobs)
        self.stack = stack if isinstance(stack, Stack) else load_stack(stack)
        if not self.stack.targets:
            raise SpecError(self.stack.manifest_path, "target", "no [[target]] tables; describe the calibration "
                            "targets (kind, squares, square_mm, ...) so that they can be found")
        self.estimator, self.refine, self.progress, self.on_edges = estimator, refine, progress, on_edges
        #: each image's targets as the first read detected them (None before it)
        self.detected: dict[int, list[Detection]] | None = None
        #: the first pass's edge profiles, the edge estimator's state among them (None: not kept)
        self.profiles: dict[str, Any] | None = {} if keep_profiles else None
        #: the settings the first read left out (``SampleTable.left_out_settings``)
        self.left_out: dict[str, str] = {}

    def read(self, airy_px: dict[str, float] | None = None) -> SampleTable:
        """The stack's samples, through each setting's Airy pattern ``airy_px`` (px) where given."""
        if airy_px is not None and self.estimator not in ("edge", "edge-disk"):
            raise InputError("estimator", self.estimator, "edge or edge-disk where diffraction is modelled",
                             "the target estimator has no diffraction model")
        if airy_px is not None:
            missing = sorted({e.setting for e in self.stack.images} - set(airy_px) - set(self.left_out))
            if missing:
                raise InputError("airy_px", missing[0], "an Airy scale for every setting of the stack")
        warming = _prewarm(self.estimator, airy_px is not None)
        first = self.detected is None
        try:
            table, detected = _measure(self.stack, self.estimator, self.fn, self.refine, self.progress, airy_px,
                                       self.detected, self.on_edges if first else None, self.profiles, self.jobs)
        finally:
            if warming is not None:
                warming.join()
        if first:
            self.detected, self.left_out = detected, dict(table.left_out_settings)
        return table

    def reread(self, table: SampleTable, which: list[int], airy_px: dict[str, float]) -> list[Any]:
        """The edge estimator again on samples ``which`` of ``table`` (a :meth:`read`) with each
        setting's Airy scale ``airy_px`` (px): their edges as they were read, their images read
        again, all in one batched solve. A quick second reading of a few edges (the pipeline's
        diffraction test), not a new table: the estimates, in order."""
        from lensfit.estimators import edge as edge_estimator

        stack = self.stack
        index = {entry.file.name: i for i, entry in enumerate(stack.images)}
        by_image: dict[int, list[int]] = {}
        for j in which:
            by_image.setdefault(index[table.samples[j].image], []).append(j)
        per_image = edge_estimator.measure_images(
            [(partial(stack.read, i), [table.edge_tasks[j] for j in js]) for i, js in by_image.items()],
            airy_px=[float(airy_px[stack.images[i].setting]) for i in by_image])
        found = {j: est for js, ests in zip(by_image.values(), per_image) for j, est in zip(js, ests)}
        return [found[j] for j in which]

    def release(self) -> None:
        """Let the kept edge profiles go (no later read needs them)."""
        self.profiles = None


def _same_objects(a: list[list[Any]], b: list[list[Any]]) -> bool:
    """Do two lists of lists hold the very same objects, in order?"""
    return len(a) == len(b) and all(len(x) == len(y) and all(p is q for p, q in zip(x, y)) for x, y in zip(a, b))


def _measure(stack: Stack, estimator: str, fn: Callable, refine: bool,
             progress: Callable[[str, int, int], None] | None, airy_px: dict[str, float] | None,
             detected: dict[int, list[Detection]] | None = None,
             on_edges: Callable[[int, int], None] | None = None,
             profiles: dict[str, Any] | None = None, jobs: int = 1) -> tuple[SampleTable, dict[int, list[Detection]]]:
    """:class:`Measurement`'s read once its arguments are checked (the edge estimator's compiled
    fits loading in the background meanwhile, :func:`_prewarm`); ``detected``: the targets of
    each image as an earlier read detected them; ``profiles``: an empty dict to keep the first
    pass's edge profiles in, or those an earlier read kept. The stages are :class:`_Run`'s.
    Returns the table and the targets as detected."""
    run = _Run(stack, estimator, fn, airy_px, progress, 3 * len(stack.images) if refine else 2 * len(stack.images))
    run.detect(detected, jobs)
    work = run.calibrate(profiles, refine)
    first = run.first_pass(work, profiles, on_edges) if refine or estimator == "edge" else {}
    if refine:
        run.refine(first)
    run.table.warnings.extend(few_informative_views(run.table.intrinsics))
    for i in range(len(stack.images)):
        run.samples_of(i, first.get(i))
        run.tick("measure")
    run.table.stage_seconds = dict(run.clock.seconds)
    return run.table, run.detected


class _Run:
    """One measure of a stack, stage by stage: :meth:`detect`, :meth:`calibrate`,
    :meth:`first_pass` (every edge in one batched solve), :meth:`refine` (the corners through the
    measured edge lines, calibrated again) and :meth:`samples_of` each image. ``table`` is what it
    makes; ``detections`` each image's targets as found (misdetections the calibration rejects
    taken out)."""

    def __init__(self, stack: Stack, estimator: str, fn: Callable, airy_px: dict[str, float] | None,
                 progress: Callable[[str, int, int], None] | None, total: int):
        targets = [Target(spec) for spec in stack.targets]
        self.targets, self.by_id = targets, {t.id: t for t in targets}
        self.estimator, self.fn, self.airy_px, self.progress, self.total, self.step = (estimator, fn, airy_px,
                                                                                      progress, total, 0)
        self.clock = StageClock()
        # Images are held between the stages while the stack fits in HOLD_BYTES, else read again
        # where needed (a stack of RAW files may not fit in memory).
        self.stack = stack.holding(HOLD_BYTES)
        self.read = self.clock.reader(self.stack.read)
        self.n = len(stack.images)
        self.detections: dict[int, list[Detection]] = {}
        # whether the first pass keeps its profiles, and the entry of an earlier round's calibration
        # the edges are kept with (:meth:`calibrate`)
        self.keeping, self.entry = False, None
        self.table = SampleTable(pixel_pitch_mm=stack.pixel_pitch_mm, image_shape=stack.shape, lens=dict(stack.lens))

    def tick(self, stage: str) -> None:
        self.step += 1
        if self.progress:
            self.progress(stage, self.step, self.total)

    def airy(self, i: int) -> float | None:
        scale = None if self.airy_px is None else self.airy_px.get(self.stack.images[i].setting)
        return None if scale is None else float(scale)  # (none for a setting left out: it has no edges)

    def detect(self, detected: dict[int, list[Detection]] | None, jobs: int) -> None:
        """Every image's targets (or those an earlier measure found: ``detected``)."""
        stack, n = self.stack, self.n
        self.detections = {i: list(found) for i, found in (detected or {}).items()}
        candidates: dict[int, list[Target]] = {}
        for i in range(n if detected is None else 0):
            entry = stack.images[i]
            candidates[i] = [t for t in self.targets if entry.targets is None or t.id in entry.targets]
            squares = [t.id for t in candidates[i] if t.kind == "slanted-edge"]
            if len(squares) > 1:
                # Each would claim the same dark square with its own printed size: wrong distances.
                raise SpecError(stack.manifest_path, f"image[{i}].targets",
                                f"{entry.file.name} may show slanted-edge targets {', '.join(squares)}, which look "
                                "alike; list the one it shows (targets = [\"ID\"]); one slanted-edge square per image")

        def detect(i: int) -> tuple[list[Detection], float, float]:
            # Reading (decoding) and OpenCV's detection release the GIL: images run in threads.
            t0 = time.perf_counter()
            img = stack.read(i)
            t1 = time.perf_counter()
            copies = detection_copies(img) if candidates[i] else []
            found = [d for d in (t.detect(img, copies) for t in candidates[i]) if d is not None]
            for d in found:
                _check_saturation(stack, i, img, d)
            return found, t1 - t0, time.perf_counter() - t1

        if detected is None:
            jobs = max(1, min(jobs, IN_FLIGHT_BYTES // max(DETECT_BYTES_PER_PX * stack.shape[0] * stack.shape[1], 1)))
            with self.clock.parallel(("read", "detect")) as spent:
                for i, (found, *seconds) in enumerate(in_threads(detect, range(n), jobs)):
                    self.detections[i] = found
                    spent(*seconds)
                    self.tick("detect")
        else:
            for i in range(n):
                self.tick("detect")
        self.detected = {i: list(found) for i, found in self.detections.items()}
        missing = [stack.images[i].file.name for i in range(n) if not self.detections[i]]
        if missing:
            self.table.warnings.append(f"no target found in {len(missing)} image(s): {', '.join(missing[:5])}")

    def calibrate_views(self, final: bool = True) -> dict[str, Any]:
        """Each setting's intrinsics (:func:`lensfit.measurement.views.calibrate_views`)."""
        return calibrate_views(self.stack, self.detections, self.table, final)

    def tasks_for(self, i: int, intrinsics: dict[str, Any]) -> tuple[list, list]:
        """Image ``i``'s edge tasks and, for each, (target id, segment, end depths, pose)."""
        if not self.detections[i]:
            return [], []
        intr = intrinsics[self.stack.images[i].setting]
        tasks, meta = [], []
        for det in self.detections[i]:
            pose = estimate_pose(det, intr)
            if pose is None:
                continue
            for seg, task, z in edge_tasks(self.by_id[det.target_id], det, pose, intr):
                tasks.append(task)
                meta.append((det.target_id, seg, z, pose))
        return tasks, meta

    def calibrate(self, profiles: dict[str, Any] | None, refine: bool) -> dict[int, tuple[list, list]] | None:
        """The calibration from the corners as detected; returns the edges it gives where an
        earlier measure of the same detections (the diffraction rounds: the same objects) kept
        them beside its profiles with the calibration and the views it left out (each round had
        calibrated them again: 0.1 s a round)."""
        table = self.table
        self.keeping = profiles == {}
        inputs = [list(self.detections[i]) for i in range(self.n)]  # held in the entry: compared by identity
        entry = profiles.get("unrefined") if profiles and refine else None
        if entry is not None and _same_objects(entry[0], inputs):
            _, kept, notes, intrinsics, work = entry
            self.detections.update({i: list(v) for i, v in kept.items()})
            table.warnings.extend(notes)
            table.intrinsics = dict(intrinsics)
            self.entry = entry  # (its edges, where a round before kept none, are kept there)
            return work
        before, self.entry = len(table.warnings), None
        with self.clock.stage("calibrate"):
            # (the uncertainty of a calibration that the refined corners replace is not needed)
            table.intrinsics = self.calibrate_views(final=not refine)
        if profiles is not None and refine:
            self.entry = profiles["unrefined"] = [inputs, {i: list(v) for i, v in self.detections.items()},
                                                  table.warnings[before:], dict(table.intrinsics), None]
        return None

    def first_pass(self, work: dict[int, tuple[list, list]] | None, profiles: dict[str, Any] | None,
                   on_edges: Callable[[int, int], None] | None) -> dict[int, tuple[list, list, list]]:
        """Every edge of the stack in one batched solve per pass, images read when needed: per
        image (tasks, their meta, estimates)."""
        # The fits loading in the background (:func:`_prewarm`) are not waited for here: each
        # compiled fit waits for its own loading (lensfit.runtime.jaxcache's lock per function), so that the
        # first pass starts once its two fits are in and the shaped fits load while it runs (on
        # the demo the process waited 0.8 s for all four before the first pass).
        from lensfit.estimators import edge as edge_estimator

        n, table = self.n, self.table
        if work is None:
            with self.clock.stage("calibrate"):
                work = {i: self.tasks_for(i, table.intrinsics) for i in range(n)}
            if self.entry is not None:  # kept with the calibration it comes from
                self.entry[4] = work
        if on_edges is not None:
            on_edges(len({e.setting for e in self.stack.images}), sum(len(w[0]) for w in work.values()))
        with self.clock.stage("measure"):
            per_image = edge_estimator.measure_images(
                [(partial(self.read, i), work[i][0]) for i in range(n)], progress=lambda k: self.tick("edges"),
                airy_px=None if self.airy_px is None else [self.airy(i) for i in range(n)],
                keep_profiles=profiles if self.keeping else None, profiles=None if self.keeping else profiles)
        return {i: (work[i][0], work[i][1], per_image[i]) for i in range(n)}

    def refine(self, first: dict[int, tuple[list, list, list]]) -> None:
        """The corners moved through the measured edge lines, and the settings calibrated again."""
        stack, table = self.stack, self.table
        before = dict(table.intrinsics)
        shifts = tone_shifts(first, [im.encoding for im in stack.images], self.by_id)
        for i in range(self.n):
            if stack.images[i].setting in table.intrinsics:  # (not a setting left out)
                self.detections[i] = refined_detections(self.detections[i], first[i],
                                                        table.intrinsics[stack.images[i].setting], self.by_id,
                                                        shift_radii=shifts[i])
        with self.clock.stage("calibrate"):
            table.intrinsics = self.calibrate_views()
        # A distortion the corners as detected did not show (OpenCV's carry ~0.1 px) but the
        # refined ones do: the lines are moved through their edges' ends again, through it.
        found = {k for k, v in table.intrinsics.items()
                 if np.any(v.distortion) and k in before and not np.any(before[k].distortion)}
        if found:
            for i in range(self.n):
                if stack.images[i].setting in found:
                    self.detections[i] = refined_detections(self.detections[i], first[i],
                                                  table.intrinsics[stack.images[i].setting], self.by_id,
                                                  fresh_poses=True, shift_radii=shifts[i])
            with self.clock.stage("calibrate"):
                table.intrinsics = self.calibrate_views()

    def estimates_of(self, i: int, tasks: list, meta: list, first: tuple[list, list, list] | None) -> tuple[list, list]:
        """Image ``i``'s blur readings for ``tasks`` (and the tasks they were read with)."""
        from lensfit.estimators import edge as edge_estimator

        if self.estimator == "edge" and first is not None:
            # Blur from the first pass (the edge lines are located in the image itself, so the
            # refined poses move nothing); distances from the refined poses.
            by_key = {(m[0], m[1].id): e for m, e in zip(first[1], first[2])}
            read_with = {(m[0], m[1].id): t for m, t in zip(first[1], first[0])}
            estimates = [by_key.get((m[0], m[1].id)) for m in meta]
            used = [read_with[(m[0], m[1].id)] if e is not None else t for m, t, e in zip(meta, tasks, estimates)]
            if any(e is None for e in estimates):
                with self.clock.stage("measure"):
                    again = edge_estimator.measure(self.read(i), tasks, airy_px=self.airy(i))
                estimates = [e if e is not None else a for e, a in zip(estimates, again)]
            return estimates, used
        with self.clock.stage("measure"):
            if not tasks:
                return [], tasks
            if self.airy_px is not None:
                return edge_estimator.measure(self.read(i), tasks, second_moment=self.estimator == "edge",
                                              airy_px=self.airy(i)), tasks
            return self.fn(self.read(i), tasks), tasks

    def samples_of(self, i: int, first: tuple[list, list, list] | None) -> None:
        """Image ``i``'s samples (and its corners, poses and edge tasks) into the table."""
        entry, table = self.stack.images[i], self.table
        table.corners_px[entry.file.name] = [(d.target_id, np.asarray(d.image_points_px, np.float64))
                                             for d in self.detections[i]]
        with self.clock.stage("calibrate"):
            tasks, meta = self.tasks_for(i, table.intrinsics)
        estimates, used = self.estimates_of(i, tasks, meta, first)
        for (tid, seg, z, pose), task, est, read_task in zip(meta, tasks, estimates, used):
            table.poses[(entry.file.name, tid)] = pose
            flags = list(est.flags)
            if pose.ambiguous:
                flags.append(Flag.POSE_AMBIGUOUS)
            if self.airy_px is not None:
                flags.append(Flag.DIFFRACTION_MODELLED)
            source = "pose"
            if entry.distance_mm is not None:
                z = np.full(3, float(entry.distance_mm))
                source = "manifest"
            middle = 0.5 * (np.asarray(task.start_px, float) + task.end_px)
            scale = task.context.get("distortion_scale", 1.0) if self.estimator != "target" else 1.0
            est = undistorted_blur(est, scale, flags)
            table.samples.append(Sample(
                image=entry.file.name, setting=entry.setting, target=tid, edge=seg.id,
                distance_mm=float(z[1]), distance_start_mm=float(z[0]), distance_end_mm=float(z[2]),
                coc_diameter_px=est.coc_diameter_px, sigma_px=est.sigma_px, estimator=self.estimator,
                flags=tuple(flags), start_px=tuple(float(v) for v in task.start_px),
                end_px=tuple(float(v) for v in task.end_px), distance_source=source,
                field_radius_px=float(np.hypot(*(middle - table.intrinsics[entry.setting].principal_point_px))),
                disk_diameter_px=est.disk_diameter_px, disk_sigma_px=est.disk_sigma_px))
            table.fit_rms.append(est.rms_residual)
            table.blur_scale.append(float(scale) if Flag.DISTORTION_SCALED in flags else 1.0)
            table.bright_offset_px.append(bright_offset(est, read_task))
            table.edge_tasks.append(EdgeTask(read_task.start_px, read_task.end_px, read_task.clear_left_px,
                                             read_task.clear_right_px, {k: v for k, v in read_task.context.items()
                                                                        if k in EDGE_CONTEXT},
                                             read_task.border_left_px, read_task.border_right_px))
