"""Engine benchmarks: the figures the engine issue asks for, on the synthetic bench street.

Renders go through :func:`semcal_ros.engine.render.view_for` with the engine's render parameters, so
the figures are those of a real calibration's full-resolution evaluation (level of detail on) and,
for comparison, the same view with every point drawn. Calibrations start from the paper's
+-2.5 m / +-5 deg and count the whole call (the map is prepared inside it).
"""

from __future__ import annotations

import os
import time
from dataclasses import replace
from typing import Callable

import numpy as np

from semcal_ros.engine.loss import LabelLoss, LossParams, loss_reference
from semcal_ros.engine.search import calibrate
from semcal_ros.engine.params import CalibrationParams, VerificationParams
from semcal_ros.engine.render.view import RenderParams
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error
from semcal_ros.engine.render import fast, prepare_map, reference, view_for
from semcal_tools.synthetic import GROUND_TRUTH, camera, street_world_of_size, target_image


def _median_ms(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up (numba compilation, caches)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1000.0)


def _starts(n: int, seed: int = 0) -> list[Pose]:
    rng = np.random.default_rng(seed)
    return [Pose.from_body_rpy_deg(GROUND_TRUTH.translation + rng.uniform(-2.5, 2.5, 3),
                                   GROUND_TRUTH.body_rpy_deg() + np.r_[0.0, rng.uniform(-5, 5, 2)])
            for _ in range(n)]


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
            "fast": _median_ms(lambda: fast.render(pmap, view), repeats),
            "fast_all_points": _median_ms(lambda: fast.render(pmap, full), repeats),
            "reference": _median_ms(lambda: reference.render(pmap, view), max(3, repeats // 5)),
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
        "fast": _median_ms(lambda: loss(rendered), repeats * 4),
        "reference": _median_ms(lambda: loss_reference(rendered, aligned, loss.table, lp), repeats),
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
