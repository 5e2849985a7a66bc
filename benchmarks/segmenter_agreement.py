"""How well each image segmenter's labels agree with the lidar, on every real scene folder.

For each real frame NAME with a folder ``NAME_ideal`` (labels.png = the first scan's point labels
projected through the true extrinsic: SemanticKITTI labels for ``*_skitti``, the geometric
labeller elsewhere) and segmenter folders ``NAME_<suffix>`` (v2 = ESPNetv2, edgetpu = EdgeTPU
DeepLab, ...), prints the share of the ideal image's labelled pixels whose segmenter label is the
same aligned class (road and sidewalk merged, vehicles kept: the KITTI agreement mapping). The
ideal image is itself only as good as its point labels (the geometric labeller is ~81 % right on
KITTI 00), so the figure ranks segmenters; it is not an accuracy. Where SemanticKITTI labels exist
(KITTI 00 frame 0) the project's point agreement (semcal_ros.segmentation.agreement) is printed
too. When a folder has probabilities.npz, its argmax agreement with labels.png and the mean top
probability are checked as well.

    .venv/bin/python benchmarks/segmenter_agreement.py /work/realscenes --suffixes v2 edgetpu
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from semcal_ros.io import files
from semcal_ros.segmentation.agreement import kitti_agreement_mapping, label_agreement
from semcal_ros.segmentation.probabilities import argmax_agrees, read_probabilities

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CLASSES = ("road", "building", "vegetation", "car")


def pixel_agreement(labels: np.ndarray, ideal: np.ndarray) -> tuple[float, dict[str, float]]:
    """Share of ideal-labelled pixels with the same aligned class; per class of the ideal."""
    from semcal_ros.engine.labels import CITYSCAPES_ID

    mapping = kitti_agreement_mapping()
    got, want = mapping.map_image(labels), mapping.map_image(ideal)
    keep = want != 255
    per = {}
    for name in CLASSES:
        sel = keep & (want == CITYSCAPES_ID[name])
        per[name] = float((got[sel] == want[sel]).mean()) if sel.any() else float("nan")
    return float((got[keep] == want[keep]).mean()), per


def point_agreement(scene: Path) -> float | None:
    """KITTI 00 frame 0 only: agreement with its SemanticKITTI points (the issue's measure)."""
    from semcal_ros.io.kitti import read_calib, read_labels, read_velodyne

    kitti = DATA / "kitti_odometry_00"
    if not scene.name.startswith("kitti00_f0") or not (kitti / "labels").is_dir():
        return None
    calib = read_calib(kitti / "calib.txt")
    result = label_agreement(files.read_label_image(scene / "labels.png"),
                             read_velodyne(kitti / "velodyne" / "000000.bin")[:, :3],
                             read_labels(kitti / "labels" / "000000.label"),
                             calib["P2"] @ calib["Tr"])
    return result.overall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="folder holding NAME_ideal and NAME_<suffix>")
    parser.add_argument("--suffixes", nargs="+", default=["v2", "edgetpu"])
    args = parser.parse_args()
    names = sorted(p.name[:-len("_ideal")] for p in args.root.glob("*_ideal"))
    head = f"{'frame':<26}" + "".join(f"{s:>34}" for s in args.suffixes)
    print(head + "\n" + "-" * len(head))
    totals: dict[str, list[float]] = {s: [] for s in args.suffixes}
    checks: dict[str, list[tuple[float, float, float]]] = {s: [] for s in args.suffixes}
    for name in names:
        ideal = files.read_label_image(args.root / f"{name}_ideal" / "labels.png")
        row = f"{name:<26}"
        for suffix in args.suffixes:
            scene = args.root / f"{name}_{suffix}"
            if not (scene / "labels.png").is_file():
                row += f"{'-':>34}"
                continue
            labels = files.read_label_image(scene / "labels.png")
            overall, per = pixel_agreement(labels, ideal)
            totals[suffix].append(overall)
            cell = f"{100 * overall:.1f} (r{100 * per['road']:.0f} b{100 * per['building']:.0f}" \
                   f" v{100 * per['vegetation']:.0f} c{100 * per['car']:.0f})"
            points = point_agreement(scene)
            if points is not None:
                cell += f" pts {100 * points:.1f}"
            row += f"{cell:>34}"
            if (scene / "probabilities.npz").is_file():
                probs = read_probabilities(scene / "probabilities.npz", labels.shape)
                agree, tied = argmax_agrees(probs, labels)
                top = float(probs.max(axis=2).astype(np.float32).mean())
                checks[suffix].append((agree, tied, top))
        print(row, flush=True)
    print("median" + " " * 20 + "".join(
        f"{(100 * np.median(v) if v else float('nan')):>34.1f}" for v in totals.values()))
    for suffix, found in checks.items():
        if found:
            agree, tied, top = (np.array(v) for v in zip(*found))
            print(f"{suffix}: probabilities.npz in {len(found)} scenes: argmax == labels on >= "
                  f"{100 * agree.min():.4f} % of labelled pixels (top tied after float16: <= "
                  f"{100 * tied.max():.4f} %), mean top probability {top.min():.2f}-"
                  f"{top.max():.2f}")


if __name__ == "__main__":
    main()
