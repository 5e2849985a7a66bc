"""Engine benchmarks: the figures the engine issue asks for, on the synthetic bench street.

Renders go through :func:`semcal_ros.engine.render.view_for` with the engine's render parameters, so
the figures are those of a real calibration's full-resolution evaluation (level of detail on) and,
for comparison, the same view with every point drawn. Calibrations start from the paper's
+-2.5 m / +-5 deg and count the whole call (the map is prepared inside it).

:func:`run_compare` times the default procedure against a plain run of the paper on the same map,
start by start and alternating, so a change to the engine shows its cost against the method
itself (a ratio within one run holds on a loaded machine; the absolute seconds do not).
"""

from __future__ import annotations

import os
import time
from dataclasses import replace
from typing import Callable

import numpy as np

from semcal_ros.engine.loss import LabelLoss, LossParams, loss_reference
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.search import EvaluationCounter, Search, calibrate
from semcal_ros.engine.params import CalibrationParams, ScheduleParams, VerificationParams
from semcal_ros.engine.render.view import RenderParams
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error
from semcal_ros.engine.render import fast, prepare_map, reference, view_for
from semcal_tools.protocol import ProtocolParams, initial_guesses
from semcal_tools.synthetic import GROUND_TRUTH, camera, street_world_of_size, target_image


def median_ms(fn: Callable[[], object], repeats: int) -> float:
    """Milliseconds, the median of ``repeats`` calls after one to warm up."""
    fn()  # warm-up (numba compilation, caches)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1000.0)


def _starts(n: int, seed: int = 0) -> list[Pose]:
    """The paper's starts (+-2.5 m, +-5 deg) around the bench street's truth."""
    return initial_guesses(GROUND_TRUTH, ProtocolParams(runs=n, keep=1, seed=seed))


def run_benchmarks(sizes: tuple[int, ...] = (100_000, 1_000_000, 3_000_000), repeats: int = 15,
                   calibrations: int = 3, calibration_sizes: tuple[int, ...] = (1_000_000, 3_500_000),
                   log: Callable[[str], None] = print) -> dict:
    cam = camera()
    results: dict = {"render_ms": {}, "image": f"{cam.width}x{cam.height}",
                     "load_average_start": os.getloadavg()[0]}
    rp = RenderParams()
    all_points = replace(rp, lod_radius=0.0)
    for n in sizes:
        world = street_world_of_size(n)
        pmap = prepare_map(world, center=GROUND_TRUTH.translation)
        view = view_for(cam, GROUND_TRUTH, pmap, rp)
        full = view_for(cam, GROUND_TRUTH, pmap, all_points)
        row = {
            "points": len(pmap),
            "drawn": int(len(reference.project_points(pmap, view)[0])),
            "fast": median_ms(lambda: fast.render(pmap, view), repeats),
            "fast_all_points": median_ms(lambda: fast.render(pmap, full), repeats),
            "reference": median_ms(lambda: reference.render(pmap, view), max(3, repeats // 5)),
        }
        results["render_ms"][str(n)] = row
        log(f"render {len(pmap):>9,d} points {cam.width}x{cam.height} ({row['drawn']:,d} drawn "
            f"after level of detail): fast {row['fast']:7.2f} ms (every point drawn: "
            f"{row['fast_all_points']:7.2f} ms), numpy reference {row['reference']:7.2f} ms")

    target = target_image(cam)
    world = street_world_of_size(1_000_000)
    pmap = prepare_map(world, center=GROUND_TRUTH.translation)
    from semcal_ros.engine.labels import LabelMapping

    aligned = LabelMapping().map_image(target)
    rendered = fast.render(pmap, view_for(cam, GROUND_TRUTH, pmap, rp))
    lp = LossParams()
    loss = LabelLoss(aligned, lp)
    results["loss_ms"] = {
        "fast": median_ms(lambda: loss(rendered), repeats * 4),
        "reference": median_ms(lambda: loss_reference(rendered, aligned, loss.table, lp), repeats),
    }
    log(f"loss {cam.width}x{cam.height}: fast {results['loss_ms']['fast']:.3f} ms, "
        f"numpy reference {results['loss_ms']['reference']:.3f} ms")

    for n in calibration_sizes:
        world = street_world_of_size(n)
        for name, params in (("single", CalibrationParams(verification=VerificationParams(starts=0))),
                             ("full_default", CalibrationParams())):
            rows = []
            for i, start in enumerate(_starts(calibrations)):
                res = calibrate(world, target, cam, start, params, seed=i)
                rows.append((res.seconds, res.evaluations, translation_error(res.pose, GROUND_TRUTH),
                             rotation_error_deg(res.pose, GROUND_TRUTH)))
            arr = np.array(rows)
            key = f"calibration_{name}_{n // 100_000 / 10:g}M"
            results[key] = {
                "points": len(world), "runs": calibrations,
                "seconds_median": float(np.median(arr[:, 0])),
                "seconds_max": float(np.max(arr[:, 0])),
                "evaluations_median": float(np.median(arr[:, 1])),
                "translation_error_cm_median": float(np.median(arr[:, 2]) * 100),
                "rotation_error_deg_median": float(np.median(arr[:, 3])),
            }
            r = results[key]
            log(f"calibration ({name.replace('_', ' ')}) on {len(world):,d} points, {calibrations} "
                f"runs from +-2.5 m / +-5 deg: median {r['seconds_median']:.2f} s (max "
                f"{r['seconds_max']:.2f}), {r['evaluations_median']:.0f} evaluations, error "
                f"{r['translation_error_cm_median']:.1f} cm / {r['rotation_error_deg_median']:.3f} deg")
    results["load_average_end"] = os.getloadavg()[0]
    return results


#: The authors' disc size: 0.195 (NDC) x 300 px / 2 at their 480x300 = 58.5 px x m at 960x600.
PAPER_LAMBDA = 0.195 * 600 / 2.0


def paper_params() -> CalibrationParams:
    """The paper's registration with this engine's parts: discs of radius lambda / d with the
    authors' lambda, plain nearest-wins z-buffer (no depth falloff), every point drawn (no level of
    detail), the masked L2 (no boundary band), one quarter-resolution stage then full resolution
    with its two restarts (tolerances 1e-4, 1e-6), one start."""
    d = CalibrationParams()
    return CalibrationParams(
        render=replace(d.render, splat_lambda=PAPER_LAMBDA, depth_falloff=0.0,
                       depth_falloff_coarse=0.0, lod_radius=0.0),
        loss=replace(d.loss, kind="l2", boundary_band_px=0.0),
        schedule=ScheduleParams(scales=(4, 1), simplex=(1.0, 0.1), fatol=(1e-4, 1e-6),
                                max_evaluations=(300, 150), restarts=(0, 2)),
        verification=replace(d.verification, starts=0))


def paper_run(world, target: np.ndarray, cam, start: Pose, mapping=None
              ) -> tuple[Pose, int, float]:
    """One plain paper run (no verification starts, no quality report): pose, evaluations and
    seconds, the map prepared inside as :func:`calibrate` does."""
    t0 = time.perf_counter()
    problem = Problem(world, target, cam, start.translation, paper_params(), mapping)
    counter = EvaluationCounter(None, None)
    search = Search(problem, counter)
    center, loss = search.coarse(start, 0, "paper")
    center, _ = search.refine(center, loss, 0, "paper", restart_first=False)
    return Pose.from_vector(center), counter.evaluations, time.perf_counter() - t0


def _compare_starts(name: str, world, target: np.ndarray, cam, truth: Pose, starts: list[Pose],
                    log: Callable[[str], None]) -> dict:
    """The default procedure and one plain paper run from each start, alternating, on one map:
    per start the seconds, their ratio and both errors; the medians returned."""
    rows = []
    for i, start in enumerate(starts):
        res = calibrate(world, target, cam, start, seed=i)
        pose, evals, seconds = paper_run(world, target, cam, start)
        rows.append((res.seconds, seconds, res.seconds / seconds,
                     translation_error(res.pose, truth) * 100, translation_error(pose, truth) * 100))
        log(f"compare {name}, start {i + 1}/{len(starts)}: default {res.seconds:.2f} s "
            f"({res.evaluations} evaluations, {rows[-1][3]:.1f} cm), paper run {seconds:.2f} s "
            f"({evals} evaluations, {rows[-1][4]:.1f} cm), ratio {rows[-1][2]:.2f}, "
            f"load {os.getloadavg()[0]:.1f}")
    arr = np.array(rows)
    r = {"points": len(world), "runs": len(starts),
         "default_seconds_median": float(np.median(arr[:, 0])),
         "paper_seconds_median": float(np.median(arr[:, 1])),
         "ratio_median": float(np.median(arr[:, 2])),
         "default_error_cm_median": float(np.median(arr[:, 3])),
         "paper_error_cm_median": float(np.median(arr[:, 4]))}
    log(f"compare {name}, {len(starts)} starts: default {r['default_seconds_median']:.2f} s "
        f"({r['default_error_cm_median']:.1f} cm), plain paper run "
        f"{r['paper_seconds_median']:.2f} s ({r['paper_error_cm_median']:.1f} cm), default / "
        f"paper {r['ratio_median']:.2f} (median of the per-start ratios)")
    return r


def run_compare(sizes: tuple[int, ...] = (1_000_000,), runs: int = 3,
                log: Callable[[str], None] = print) -> dict:
    """The default procedure (verification starts and quality report included) against one plain
    paper run (:func:`paper_run`), from the same starts on the same map, alternating."""
    cam = camera()
    target = target_image(cam)
    calibrate(street_world_of_size(100_000), target, cam, _starts(1)[0], seed=0)  # compile
    out: dict = {"load_average_start": os.getloadavg()[0]}
    for n in sizes:
        world = street_world_of_size(n)
        out[f"compare_{n // 100_000 / 10:g}M"] = _compare_starts(
            f"{len(world):,d} points", world, target, cam, GROUND_TRUTH, _starts(runs), log)
    out["load_average_end"] = os.getloadavg()[0]
    return out


def run_compare_scenes(folders: list, runs: int = 3, log: Callable[[str], None] = print) -> dict:
    """:func:`run_compare` on scene folders (the catalogue's: map.ply, labels.png,
    camera_info.yaml, ground_truth.yaml): from the paper's starts around the truth (the
    evaluation protocol's first ``runs``), the default procedure and one plain paper run,
    alternating start by start, with the ratio of their seconds."""
    from pathlib import Path

    from semcal_ros.io import files, ply

    out: dict = {"load_average_start": os.getloadavg()[0]}
    for folder in map(Path, folders):
        world = ply.read_ply(folder / "map.ply")
        truth = files.read_pose(folder / "ground_truth.yaml")
        out[folder.name] = _compare_starts(
            f"{folder.name} ({len(world):,d} points)", world,
            files.read_label_image(folder / "labels.png"),
            files.read_camera_info(folder / "camera_info.yaml"), truth,
            initial_guesses(truth, ProtocolParams(runs=runs, keep=1)), log)
    out["load_average_end"] = os.getloadavg()[0]
    return out
