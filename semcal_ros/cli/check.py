"""``semcal check``: is a calibration still right? One drift check from files (docs/drift.md).

Exit codes: 0 the calibration holds (ok), 3 drift (warn or error), 1 cannot judge (no usable
image, the map covers too little of it) or bad input.
"""

from __future__ import annotations

import argparse

EXIT_OK, EXIT_CANNOT_JUDGE, EXIT_DRIFT = 0, 1, 3


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "check", help="check a calibration against a new label image (drift)",
        description="Check a camera's calibration against its newest label image: the loss at "
                    "the calibration against a small search around it. Exit 0: ok, 3: drift, "
                    "1: cannot judge.")
    p.add_argument("--map", required=True, help="map.ply (float x, y, z, ushort label)")
    p.add_argument("--labels", required=True, help="labels.png: the camera's newest label image")
    p.add_argument("--camera-info", required=True, help="camera_info.yaml (ROS format)")
    p.add_argument("--calibration", required=True,
                   help="the calibration to check: a pose YAML (e.g. semcal calibrate's result)")
    p.add_argument("--reference",
                   help="a label image known to match the calibration (e.g. the one it was "
                        "calibrated from): drift is counted from where the check ends on it")
    p.add_argument("--config", help="ROS 2 parameter file whose engine: group the check uses "
                                    "(as semcal calibrate --config)")
    p.add_argument("--drift-config", help="parameter file with the check's drift: group "
                                          "(default: config/calibration_monitor.yaml's values)")
    p.add_argument("--label-mapping", help="YAML changing the class alignment")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from semcal_ros.engine.drift import DriftChecker, DriftParams
    from semcal_ros.engine.drift_watch import DriftWatch
    from semcal_ros.io import files, ply
    from semcal_ros.engine.labels import LabelMapping
    from semcal_ros.engine.params import CalibrationParams

    engine = CalibrationParams.from_file(args.config)
    drift = DriftParams.from_file(args.drift_config)
    mapping = LabelMapping.from_yaml(args.label_mapping) if args.label_mapping else None
    camera = files.read_camera_info(args.camera_info)
    calibrated = files.read_pose(args.calibration)
    labels = files.read_label_image(args.labels)
    reference_labels = files.read_label_image(args.reference) if args.reference else None
    cloud = ply.read_ply(args.map)
    if len(cloud.finite()) < len(cloud):
        raise ValueError(f"{args.map}: map contains {len(cloud) - len(cloud.finite())} NaN or "
                         f"infinite points")
    try:  # the map cropped around the calibration holds nothing: nothing to judge from
        checker = DriftChecker(cloud, camera, calibrated, engine, drift, mapping)
    except ValueError as exc:
        print(f"CANNOT JUDGE: {' '.join(str(exc).split())}")
        return EXIT_CANNOT_JUDGE
    # the monitor's rule (DriftWatch): the reference counts only if it found no drift itself
    watch = DriftWatch(confirm=1, take_reference=reference_labels is not None)
    if reference_labels is not None:
        first = watch.check(checker, reference_labels).report
        if not first.judged:
            print(f"reference: cannot judge: {first.message}")
            return EXIT_CANNOT_JUDGE
        if watch.reference is None:
            print(f"reference: not used, it shows drift itself ({first.message})")
    report = watch.check(checker, labels).report
    print(report.summary())
    if report.judged:
        t = report.drift_xyz_m
        print(f"drift: {report.drift_translation_m * 100:.1f} cm (x {t[0] * 100:+.1f}, "
              f"y {t[1] * 100:+.1f}, z {t[2] * 100:+.1f} cm, map frame), "
              f"{report.drift_rotation_deg:.3f} deg")
    if not report.judged:
        return EXIT_CANNOT_JUDGE
    return EXIT_DRIFT if report.level in ("warn", "error") else EXIT_OK
