"""From an image stack to samples of (distance from the lens, blur-disk diameter, uncertainty).

Pipeline: read the manifest -> detect every target in every image -> calibrate intrinsics per
lens setting (focal length in px; shared principal point and distortion) -> pose of each
target in each image -> the straight edges of each target, with the distance of their ends and
middle from the lens plane -> a blur estimator on each edge.

``measure(stack)`` returns a :class:`SampleTable`; the CLI writes it as CSV or JSON.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from functools import partial
from pathlib import Path
from typing import Any, Callable

import numpy as np

from lensfit.clock import StageClock
from lensfit.calibration import calibrate, estimate_pose, few_informative_views, known_intrinsics, outlier_views
from lensfit.errors import InputError, SpecError
from lensfit.estimators import EdgeTask, get_estimator
from lensfit.parallel import check_jobs, in_threads
from lensfit.sample_table import Sample, SampleTable
from lensfit.stack import Stack, load_stack
from lensfit.edge_geometry import bow_margin, edge_tasks, refine_corners, unbowed
from lensfit.targets import Detection, Target, detection_copies

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
#: and diffraction rounds, 11 of its 35 s); a larger one (many RAW files) is read again where
#: needed, a few images in memory at once.
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
            airy_px: dict[str, float] | None = None, detected: SampleTable | None = None,
            on_edges: Callable[[int, int], None] | None = None, keep_profiles: bool = False,
            jobs: int | None = None) -> SampleTable:
    """Measure blur versus distance on every target edge of a stack.

    Parameters
    ----------
    stack : Stack or str or Path
        A :class:`~lensfit.stack.Stack`, or the path of a stack folder.
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
        ``lensfit.diffraction``, ``lensfit.pipeline``).
    detected : SampleTable, optional
        A table this process measured of the same stack: its targets as detected are taken
        instead of detecting them again (the diffraction rounds of ``lensfit.pipeline``; the
        corners are refined, the intrinsics calibrated and the blur read afresh: from its edge
        profiles where it kept them and its edges are these, ``keep_profiles``).
    on_edges : callable, optional
        Called with the number of settings and of edges once the edges are known, before they
        are measured (``lensfit.pipeline`` starts loading the fit's compiled functions for them
        there, in the background).
    keep_profiles : bool
        Keep the edge estimator's profiles in the table (``SampleTable.profiles``) for a later
        measure with the Airy pattern (``detected``); memory: about 4 kB an edge.
    jobs : int, optional
        Images read and searched for targets at once, in threads (default: the cores this
        process may use; ``lensfit.parallel``). The results are the same whatever it is.

    Returns
    -------
    SampleTable

    Raises
    ------
    lensfit.errors.SpecError, lensfit.errors.InputError
        Unreadable or inconsistent input, saturated targets, a setting that cannot be calibrated.

    Examples
    --------
    >>> from lensfit.measure import measure
    >>> table = measure("out/demo")                     # doctest: +SKIP
    >>> table.write("samples.csv")                      # doctest: +SKIP
    """
    fn = get_estimator(estimator)
    jobs = check_jobs(jobs)
    if airy_px is not None and estimator not in ("edge", "edge-disk"):
        raise InputError("estimator", estimator, "edge or edge-disk where diffraction is modelled",
                         "the target estimator has no diffraction model")
    if not isinstance(stack, Stack):
        stack = load_stack(stack)
    if airy_px is not None:
        missing = sorted({e.setting for e in stack.images} - set(airy_px))
        if missing:
            raise InputError("airy_px", missing[0], "an Airy scale for every setting of the stack")

    if not stack.targets:
        raise SpecError(stack.manifest_path, "target", "no [[target]] tables; describe the calibration targets "
                        "(kind, squares, square_mm, ...) so that they can be found")
    warming = _prewarm(estimator, airy_px is not None)
    try:
        same = detected is not None and len(detected.detections) == len(stack.images)
        return _measure(stack, estimator, fn, refine, progress, airy_px,
                        detected.detections if same else None, on_edges,
                        {} if keep_profiles else detected.profiles if same else None, jobs)
    finally:
        if warming is not None:
            warming.join()


def remeasure(stack: Stack, table: SampleTable, which: list[int], airy_px: dict[str, float]) -> list[Any]:
    """The edge estimator again on samples ``which`` of ``table`` (a :func:`measure` of ``stack``
    in this process) with each setting's Airy scale ``airy_px`` (px): their edges as they were
    read, their images read again, all in one batched solve. A quick second reading of a few
    edges (``lensfit.pipeline``'s diffraction test), not a new table: the estimates, in order."""
    from lensfit.estimators import edge as edge_estimator

    index = {entry.file.name: i for i, entry in enumerate(stack.images)}
    by_image: dict[int, list[int]] = {}
    for j in which:
        by_image.setdefault(index[table.samples[j].image], []).append(j)
    per_image = edge_estimator.measure_images(
        [(partial(stack.read, i), [table.edge_tasks[j] for j in js]) for i, js in by_image.items()],
        airy_px=[float(airy_px[stack.images[i].setting]) for i in by_image])
    found = {j: est for js, ests in zip(by_image.values(), per_image) for j, est in zip(js, ests)}
    return [found[j] for j in which]


def _same_objects(a: list[list[Any]], b: list[list[Any]]) -> bool:
    """Do two lists of lists hold the very same objects, in order?"""
    return len(a) == len(b) and all(len(x) == len(y) and all(p is q for p, q in zip(x, y)) for x, y in zip(a, b))


def _measure(stack: Stack, estimator: str, fn: Callable, refine: bool,
             progress: Callable[[str, int, int], None] | None, airy_px: dict[str, float] | None,
             detected: dict[int, list[Detection]] | None = None,
             on_edges: Callable[[int, int], None] | None = None,
             profiles: dict[str, Any] | None = None, jobs: int = 1) -> SampleTable:
    """:func:`measure` once its arguments are checked (the edge estimator's compiled fits loading
    in the background meanwhile, :func:`_prewarm`); ``detected``: the targets of each image as an
    earlier measure of the stack detected them; ``on_edges``: see :func:`measure`; ``profiles``:
    an empty dict to keep the first pass's edge profiles in, or those an earlier measure kept
    (``SampleTable.profiles``), carried on to this table."""
    def airy(i):
        return None if airy_px is None else float(airy_px[stack.images[i].setting])
    targets = [Target(spec) for spec in stack.targets]
    by_id = {t.id: t for t in targets}
    n = len(stack.images)
    clock = StageClock()
    # Images are held between the stages while the stack fits in HOLD_BYTES, else read again where
    # needed (a stack of RAW files may not fit in memory).
    stack = stack.holding(HOLD_BYTES)
    read = clock.reader(stack.read)
    total = 3 * n if refine else 2 * n
    step = [0]

    def tick(stage):
        step[0] += 1
        if progress:
            progress(stage, step[0], total)

    detections: dict[int, list[Detection]] = {i: list(found) for i, found in (detected or {}).items()}
    candidates: dict[int, list[Target]] = {}
    for i in range(n if detected is None else 0):
        entry = stack.images[i]
        candidates[i] = [t for t in targets if entry.targets is None or t.id in entry.targets]
        squares = [t.id for t in candidates[i] if t.kind == "slanted-edge"]
        if len(squares) > 1:
            # Each would claim the same dark square with its own printed size: wrong distances.
            raise SpecError(stack.manifest_path, f"image[{i}].targets",
                            f"{entry.file.name} may show slanted-edge targets {', '.join(squares)}, which look alike; "
                            "list the one it shows (targets = [\"ID\"]); one slanted-edge square per image")

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
        with clock.parallel(("read", "detect")) as spent:
            for i, (found, *seconds) in enumerate(in_threads(detect, range(n), jobs)):
                detections[i] = found
                spent(*seconds)
                tick("detect")
    else:
        for i in range(n):
            tick("detect")
    table = SampleTable(pixel_pitch_mm=stack.pixel_pitch_mm, image_shape=stack.shape,
                        detections={i: list(found) for i, found in detections.items()}, lens=dict(stack.lens))
    missing = [stack.images[i].file.name for i in range(n) if not detections[i]]
    if missing:
        table.warnings.append(f"no target found in {len(missing)} image(s): {', '.join(missing[:5])}")

    def calibrate_all(final: bool = True):
        views: dict[str, list[tuple[int, Detection]]] = {}
        for i in range(n):
            views.setdefault(stack.images[i].setting, []).extend((i, d) for d in detections[i])
        known = {k: known_intrinsics(v, stack.shape) for k, v in stack.intrinsics.items()}
        todo = {k: v for k, v in views.items() if k not in known}
        for label, bad in outlier_views({k: [d for _, d in v] for k, v in todo.items()}, stack.shape).items():
            for j, rms, median in bad:  # misdetections: left out of the calibration and the samples
                i, det = todo[label][j]
                detections[i] = [d for d in detections[i] if d is not det]
                table.warnings.append(f"{stack.images[i].file.name}: target {det.target_id!r} left out, its corners "
                                      f"reproject {rms:.2g} px off the calibration of setting {label!r} (median view "
                                      f"{median:.2g} px): a misdetection, or markers misread under heavy blur")
            dropped = {j for j, _, _ in bad}
            todo[label] = [view for j, view in enumerate(todo[label]) if j not in dropped]
        todo = {k: [d for _, d in v] for k, v in todo.items()}
        return {**(calibrate(todo, stack.shape, jackknife=final) if todo else {}), **known}

    def tasks_for(i, intrinsics):
        intr = intrinsics[stack.images[i].setting]
        tasks, meta = [], []
        for det in detections[i]:
            pose = estimate_pose(det, intr)
            if pose is None:
                continue
            for seg, task, z in edge_tasks(by_id[det.target_id], det, pose, intr):
                tasks.append(task)
                meta.append((det.target_id, seg, z, pose))
        return tasks, meta

    # The calibration from the corners as detected, the views it left out and the edges it gives
    # are those of an earlier measure of the same detections (the diffraction rounds: the same
    # objects), kept beside the profiles: each round had calibrated them again (0.1 s a round).
    keeping = profiles == {}
    inputs = [list(detections[i]) for i in range(n)]  # held in the entry: compared by identity
    entry = profiles.get("unrefined") if profiles and refine else None
    if entry is not None and _same_objects(entry[0], inputs):
        _, kept, notes, intrinsics, work = entry
        detections.update({i: list(v) for i, v in kept.items()})
        table.warnings.extend(notes)
        table.intrinsics = dict(intrinsics)
    else:
        before, entry, work = len(table.warnings), None, None
        with clock.stage("calibrate"):
            # (the uncertainty of a calibration that the refined corners replace is not needed)
            table.intrinsics = calibrate_all(final=not refine)
        if profiles is not None and refine:
            entry = profiles["unrefined"] = [inputs, {i: list(v) for i, v in detections.items()},
                                             table.warnings[before:], dict(table.intrinsics), None]
    # The fits loading in the background (:func:`_prewarm`) are not waited for here: each compiled fit
    # waits for its own loading (lensfit.aot's lock per function), so that the first pass starts
    # once its two fits are in and the shaped fits load while it runs (on the demo the process
    # waited 0.8 s for all four before the first pass).
    from lensfit.estimators import edge as edge_estimator

    first: dict[int, tuple[list, list, list]] = {}
    if refine or estimator == "edge":
        # Every edge of the stack in one batched solve per pass; images read when needed.
        if work is None:
            with clock.stage("calibrate"):
                work = {i: tasks_for(i, table.intrinsics) for i in range(n)}
            if entry is not None:  # kept with the calibration it comes from
                entry[4] = work
        if on_edges is not None:
            on_edges(len({e.setting for e in stack.images}), sum(len(w[0]) for w in work.values()))
        with clock.stage("measure"):
            per_image = edge_estimator.measure_images([(partial(read, i), work[i][0]) for i in range(n)],
                                                      progress=lambda k: tick("edges"),
                                                      airy_px=None if airy_px is None else [airy(i) for i in range(n)],
                                                      keep_profiles=profiles if keeping else None,
                                                      profiles=None if keeping else profiles)
        table.profiles = profiles if profiles else None
        for i in range(n):
            first[i] = (work[i][0], work[i][1], per_image[i])
    if refine:
        before = dict(table.intrinsics)
        for i in range(n):
            detections[i] = _refined(detections[i], first[i], table.intrinsics[stack.images[i].setting], by_id)
        with clock.stage("calibrate"):
            table.intrinsics = calibrate_all()
        # A distortion the corners as detected did not show (OpenCV's carry ~0.1 px) but the refined
        # ones do: the lines are moved through their edges' ends again, through that distortion.
        found = {k for k, v in table.intrinsics.items()
                 if np.any(v.distortion) and k in before and not np.any(before[k].distortion)}
        if found:
            for i in range(n):
                if stack.images[i].setting in found:
                    detections[i] = _refined(detections[i], first[i], table.intrinsics[stack.images[i].setting],
                                             by_id, fresh_poses=True)
            with clock.stage("calibrate"):
                table.intrinsics = calibrate_all()
    table.warnings.extend(few_informative_views(table.intrinsics))
    for i in range(n):
        entry = stack.images[i]
        table.corners_px[entry.file.name] = [(d.target_id, np.asarray(d.image_points_px, np.float64))
                                             for d in detections[i]]
        with clock.stage("calibrate"):
            tasks, meta = tasks_for(i, table.intrinsics)
        if estimator == "edge" and i in first:
            # Blur from the first pass (the edge lines are located in the image itself, so the
            # refined poses move nothing); distances from the refined poses.
            by_key = {(m[0], m[1].id): e for m, e in zip(first[i][1], first[i][2])}
            read_with = {(m[0], m[1].id): t for m, t in zip(first[i][1], first[i][0])}
            estimates = [by_key.get((m[0], m[1].id)) for m in meta]
            used = [read_with[(m[0], m[1].id)] if e is not None else t for m, t, e in zip(meta, tasks, estimates)]
            if any(e is None for e in estimates):
                with clock.stage("measure"):
                    again = edge_estimator.measure(read(i), tasks, airy_px=airy(i))
                estimates = [e if e is not None else a for e, a in zip(estimates, again)]
        else:
            used = tasks
            with clock.stage("measure"):
                if not tasks:
                    estimates = []
                elif airy_px is not None:
                    estimates = edge_estimator.measure(read(i), tasks, second_moment=estimator == "edge",
                                                       airy_px=airy(i))
                else:
                    estimates = fn(read(i), tasks)
        for (tid, seg, z, pose), task, est, read_task in zip(meta, tasks, estimates, used):
            table.poses[(entry.file.name, tid)] = pose
            flags = list(est.flags)
            if pose.ambiguous:
                flags.append("pose_ambiguous")
            if airy_px is not None:
                flags.append("diffraction_modelled")
            source = "pose"
            if entry.distance_mm is not None:
                z = np.full(3, float(entry.distance_mm))
                source = "manifest"
            middle = 0.5 * (np.asarray(task.start_px, float) + task.end_px)
            est = _undistorted_blur(est, task.context.get("distortion_scale", 1.0) if estimator != "target" else 1.0,
                                    flags)
            table.samples.append(Sample(
                image=entry.file.name, setting=entry.setting, target=tid, edge=seg.id,
                distance_mm=float(z[1]), distance_start_mm=float(z[0]), distance_end_mm=float(z[2]),
                coc_diameter_px=est.coc_diameter_px, sigma_px=est.sigma_px, estimator=estimator,
                flags=";".join(flags), start_px=tuple(float(v) for v in task.start_px),
                end_px=tuple(float(v) for v in task.end_px), distance_source=source,
                field_radius_px=float(np.hypot(*(middle - table.intrinsics[entry.setting].principal_point_px))),
                disk_diameter_px=est.disk_diameter_px, disk_sigma_px=est.disk_sigma_px))
            table.fit_rms.append(est.rms_residual)
            table.edge_tasks.append(EdgeTask(read_task.start_px, read_task.end_px, read_task.clear_left_px,
                                             read_task.clear_right_px, {k: v for k, v in read_task.context.items()
                                                                        if k in EDGE_CONTEXT}))
        tick("measure")
    table.stage_seconds = dict(clock.seconds)
    return table


#: The distortion scales (lensfit.edge_geometry.distortion_scale) a blur reading is taken through:
#: beyond them the calibrated model is folding or far outside what it was fitted on.
DISTORTION_SCALE_RANGE = (0.2, 5.0)


def _refined(detections: list[Detection], first: tuple[list, list, list], intr, by_id: dict[str, Target],
             fresh_poses: bool = False) -> list[Detection]:
    """An image's detections with their corners refined from the edge lines of the first pass
    (``first``: its tasks, their (target, segment, depths, pose) and the readings), each line
    moved through its edge's true ends where ``intr``'s distortion bows the edge
    (:func:`lensfit.edge_geometry.unbowed`), through the pose the edge was measured with or, with
    ``fresh_poses``, the detection's pose under ``intr``."""
    tasks, meta, estimates = first
    out = []
    for det in detections:
        pose_now = estimate_pose(det, intr) if fresh_poses else None
        lines = {seg.id: (unbowed(est.line_px, seg, pose if pose_now is None else pose_now, intr, bow_margin(task, est)),
                          est.coc_diameter_px, est.line_cov_px2)
                 for task, (tid, seg, _, pose), est in zip(tasks, meta, estimates)
                 if tid == det.target_id and est.line_px is not None}
        out.append(refine_corners(det, by_id[det.target_id], lines))
    return out


def _undistorted_blur(est: Any, scale: float, flags: list[str]) -> Any:
    """An edge's blur reading in the undistorted image's pixels, where the CoC model lives: the
    image's reading over the distortion's ``scale`` across the edge (its sigma and the uniform
    disk's reading with it; flag ``distortion_scaled``); none where the scale is out of
    ``DISTORTION_SCALE_RANGE`` (flag ``distortion_extreme``). ``flags`` is extended in place."""
    if scale == 1.0 or est.coc_diameter_px is None:
        return est
    if not (math.isfinite(scale) and DISTORTION_SCALE_RANGE[0] <= scale <= DISTORTION_SCALE_RANGE[1]):
        flags.append("distortion_extreme")
        return dataclasses.replace(est, coc_diameter_px=None, sigma_px=None)
    flags.append("distortion_scaled")

    def over(v):
        return None if v is None else v / scale

    return dataclasses.replace(est, coc_diameter_px=over(est.coc_diameter_px), sigma_px=over(est.sigma_px),
                               disk_diameter_px=over(est.disk_diameter_px), disk_sigma_px=over(est.disk_sigma_px))
