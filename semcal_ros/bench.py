"""Engine benchmarks: the figures the engine issue asks for, measured on the synthetic street."""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from semcal_ros.labels import LabelMapping
from semcal_ros.loss import LabelLoss, LossParams, loss_reference
from semcal_ros.optimize import calibrate
from semcal_ros.params import CalibrationParams, VerificationParams
from semcal_ros.pose import Pose, rotation_error_deg, translation_error
from semcal_ros.render import make_view, prepare_map
from semcal_ros.render import fast, reference
from semcal_ros.synthetic import GROUND_TRUTH, camera, street_world_of_size, target_image


def _median_ms(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up (numba compilation, caches)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1000.0)


def run_benchmarks(sizes: tuple[int, ...] = (100_000, 1_000_000, 3_000_000), repeats: int = 15,
                   calibrations: int = 3, log: Callable[[str], None] = print) -> dict:
    cam = camera()
    results: dict = {"render_ms": {}, "image": f"{cam.width}x{cam.height}"}
    for n in sizes:
        world = street_world_of_size(n)
        pmap = prepare_map(world, center=GROUND_TRUTH.translation)
        view = make_view(cam, GROUND_TRUTH, pmap.origin, 32.0, 8.0, depth_falloff=0.05)
        row = {
            "points": len(pmap),
            "fast": _median_ms(lambda: fast.render(pmap, view), repeats),
            "reference": _median_ms(lambda: reference.render(pmap, view), max(3, repeats // 3)),
        }
        results["render_ms"][str(n)] = row
        log(f"render {len(pmap):>9,d} points {cam.width}x{cam.height}: fast {row['fast']:7.2f} ms, "
            f"numpy reference {row['reference']:7.2f} ms")

    mapping = LabelMapping()
    target = target_image(cam)
    aligned = mapping.map_image(target)
    world = street_world_of_size(1_000_000)
    pmap = prepare_map(world, center=GROUND_TRUTH.translation)
    rendered = fast.render(pmap, make_view(cam, GROUND_TRUTH, pmap.origin, 32.0, 8.0))
    lp = LossParams()
    loss = LabelLoss(aligned, lp)
    results["loss_ms"] = {
        "fast": _median_ms(lambda: loss(rendered), repeats * 4),
        "reference": _median_ms(lambda: loss_reference(rendered, aligned, loss.table, lp), repeats),
    }
    log(f"loss {cam.width}x{cam.height}: fast {results['loss_ms']['fast']:.3f} ms, "
        f"numpy reference {results['loss_ms']['reference']:.3f} ms")

    rng = np.random.default_rng(0)
    for name, params in (("single", CalibrationParams(verification=VerificationParams(starts=0))),
                         ("full_default", CalibrationParams())):
        rows = []
        for i in range(calibrations):
            start = Pose.from_body_rpy_deg(
                GROUND_TRUTH.translation + rng.uniform(-2.5, 2.5, 3),
                GROUND_TRUTH.body_rpy_deg() + np.r_[0.0, rng.uniform(-5, 5, 2)])
            res = calibrate(world, target, cam, start, params, mapping, seed=i)
            rows.append((res.seconds, res.evaluations, translation_error(res.pose, GROUND_TRUTH),
                         rotation_error_deg(res.pose, GROUND_TRUTH)))
        arr = np.array(rows)
        results[f"calibration_{name}"] = {
            "points": len(world), "runs": calibrations,
            "seconds_median": float(np.median(arr[:, 0])),
            "evaluations_median": float(np.median(arr[:, 1])),
            "translation_error_cm_median": float(np.median(arr[:, 2]) * 100),
            "rotation_error_deg_median": float(np.median(arr[:, 3])),
        }
        r = results[f"calibration_{name}"]
        log(f"calibration ({name.replace('_', ' ')}) on {len(world):,d} points, {calibrations} runs "
            f"from +-2.5 m / +-5 deg: median {r['seconds_median']:.2f} s, "
            f"{r['evaluations_median']:.0f} evaluations, error {r['translation_error_cm_median']:.1f} cm"
            f" / {r['rotation_error_deg_median']:.3f} deg")
    return results
