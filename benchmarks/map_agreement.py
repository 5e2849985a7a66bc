"""Per-class agreement of a scene's map labels with its label image at the true pose, as the
calibration's quality report prints it (``semcal_ros.engine.quality.label_agreement``: share of
the pixels where the map drew a point and the image has a class, per image class), for real
scene folders (``benchmarks/make_real_scenes.sh``).

    .venv/bin/python benchmarks/map_agreement.py /work/scenes/pjlab_*_esp [--relabel]

``--relabel`` labels the scene's scan again with the geometric labeller of this checkout
(the shipped forest, or ``--model``) before rendering: a one-scan folder's map.ply holds the voxel
centroids of the scan's points in the lidar frame, so each map point takes the new label of its
nearest scan point (``--relabel --model`` with the folder's own forest measures what that
transfer changes). Scenes with several scans are refused with --relabel.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

CLASSES = ("road", "sidewalk", "building", "vegetation", "terrain", "pole", "car", "fence")


def relabelled_map(folder: Path, model: Path | None):
    """The folder's map with each point's label from this checkout's labeller on its scan."""
    import yaml
    from scipy.spatial import cKDTree

    from semcal_ros.io import lidar_scans, ply
    from semcal_ros.segmentation.geometric import label_scan

    scene = yaml.safe_load((folder / "scene.yaml").read_text())
    if len(scene["scans"]) != 1:
        raise SystemExit(f"{folder}: {len(scene['scans'])} scans; --relabel takes one")
    scan_path = Path(scene["scans"][0])
    if not scan_path.is_absolute():
        scan_path = (Path(__file__).resolve().parents[1] / scan_path).resolve()
    cloud = lidar_scans.read_lidar_scan(scan_path)
    labels = label_scan(cloud.xyz, cloud.extra.get("intensity"), model=model)
    cmap = ply.read_ply(folder / "map.ply")
    dist, idx = cKDTree(np.asarray(cloud.xyz, np.float64)).query(np.asarray(cmap.xyz, np.float64))
    if np.percentile(dist, 99) > 0.15:
        raise SystemExit(f"{folder}: map points are not the scan's points (99th percentile "
                         f"distance {np.percentile(dist, 99):.3f} m)")
    cmap.label[:] = labels[idx]
    return cmap


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", type=Path, nargs="+")
    ap.add_argument("--relabel", action="store_true")
    ap.add_argument("--model", type=Path)
    args = ap.parse_args()

    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.problem import Problem
    from semcal_ros.engine.quality import label_agreement
    from semcal_ros.io.files import read_camera_info, read_label_image, read_pose
    from semcal_ros.io.ply import read_ply

    print("| scene | overall | " + " | ".join(CLASSES) + " | map shares |")
    print("|---|---|" + "---|" * len(CLASSES) + "---|")
    for folder in args.scenes:
        cmap = relabelled_map(folder, args.model) if args.relabel else read_ply(folder / "map.ply")
        truth = read_pose(folder / "ground_truth.yaml")
        config = folder / "calibrator.yaml"
        params = CalibrationParams.from_file(str(config) if config.is_file() else None)
        problem = Problem(cmap, read_label_image(folder / "labels.png"),
                          read_camera_info(folder / "camera_info.yaml"), truth.translation, params)
        overall, per_class = label_agreement(problem.render(truth), problem.target,
                                             params.loss.crop_top)
        from semcal_ros.engine.labels import SEMANTIC_KITTI as KITTI_NAME

        ids, counts = np.unique(cmap.label, return_counts=True)
        order = np.argsort(-counts)[:5]
        shares = ", ".join(f"{KITTI_NAME.get(int(ids[i]), str(ids[i]))} "
                           f"{100 * counts[i] / counts.sum():.0f}" for i in order)
        cells = " | ".join(f"{100 * per_class[c]:.0f}" if c in per_class else "-" for c in CLASSES)
        print(f"| {folder.name} | {100 * overall:.1f} | {cells} | {shares} |")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
