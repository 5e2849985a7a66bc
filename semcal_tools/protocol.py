"""The paper's evaluation protocol on a scene folder (Table I of Tsaregorodtsev et al. 2022).

Many calibrations start from the ground truth plus uniform noise (+-2.5 m in x, y, z and +-5 deg
in pitch and yaw, roll kept); the runs with the lowest final loss are kept (10 of 30) and their
mean translation error norm and mean geodesic rotation error are reported — the loss is known
without ground truth, so keeping low-loss runs is what a user could do too. The same means over
all runs, the success rate (< 5 cm and < 0.1 deg) and the time per run say how often a single
calibration would have done as well. Each run is the engine's full default procedure from that
start (its own verification starts included), as a user would run it; ``single`` gives the figure
of one schedule per start.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from semcal_ros.io.files import (
    pose_from_dict, pose_to_dict, read_camera_info, read_label_image, read_pose,
)
from semcal_ros.io.ply import read_ply
from semcal_ros.engine.labels import LabelMapping
from semcal_ros.engine.loss import LOSS_KINDS
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error


@dataclass(frozen=True)
class ProtocolParams:
    runs: int = 30
    keep: int = 10
    noise_xyz_m: float = 2.5
    noise_pitch_deg: float = 5.0
    noise_yaw_deg: float = 5.0
    success_m: float = 0.05
    success_deg: float = 0.1
    seed: int = 0

    def __post_init__(self) -> None:
        if self.runs < 1:
            raise ValueError(f"--runs must be at least 1, got {self.runs}")
        if not 1 <= self.keep <= self.runs:
            raise ValueError(f"--keep must be between 1 and --runs ({self.runs}), got {self.keep}")


@dataclass(frozen=True)
class Summary:
    """Statistics of one scene and loss (errors in cm and deg, as the paper reports them)."""

    runs: int
    keep: int
    kept_translation_cm: float
    kept_rotation_deg: float
    all_translation_cm: float
    all_rotation_deg: float
    median_translation_cm: float
    median_rotation_deg: float
    success_rate: float  # over all runs
    kept_success_rate: float
    seconds_per_run: float


def summarize(losses: np.ndarray, translation_m: np.ndarray, rotation_deg: np.ndarray,
              seconds: np.ndarray, keep: int, success_m: float = 0.05,
              success_deg: float = 0.1) -> Summary:
    """The protocol's numbers from per-run final losses, errors and durations.

    Kept are the ``keep`` runs of lowest loss (ties: the earlier run). Pure function, so the
    statistics can be checked by hand.
    """
    losses, t, r, s = (np.asarray(a, float) for a in (losses, translation_m, rotation_deg, seconds))
    n = len(losses)
    if not n or any(len(a) != n for a in (t, r, s)):
        raise ValueError("losses, errors and durations must be non-empty and of equal length")
    if not 1 <= keep <= n:
        raise ValueError(f"keep must be in 1..{n}, got {keep}")
    kept = np.argsort(losses, kind="stable")[:keep]
    ok = (t < success_m) & (r < success_deg)
    return Summary(
        runs=n, keep=keep,
        kept_translation_cm=float(t[kept].mean() * 100), kept_rotation_deg=float(r[kept].mean()),
        all_translation_cm=float(t.mean() * 100), all_rotation_deg=float(r.mean()),
        median_translation_cm=float(np.median(t) * 100), median_rotation_deg=float(np.median(r)),
        success_rate=float(ok.mean()), kept_success_rate=float(ok[kept].mean()),
        seconds_per_run=float(s.mean()),
    )


def initial_guesses(truth: Pose, protocol: ProtocolParams) -> list[Pose]:
    """``runs`` starts: uniform noise in x, y, z, pitch and yaw around the truth (seeded). The
    bench uses these too; :func:`semcal_ros.engine.pose.perturbed_initial` (one demo start, angles
    drawn first) is kept apart so that scenes and stored protocol figures stay reproducible."""
    rng = np.random.default_rng(protocol.seed)
    rpy = truth.body_rpy_deg()
    out = []
    for _ in range(protocol.runs):
        dt = rng.uniform(-protocol.noise_xyz_m, protocol.noise_xyz_m, 3)
        dp = rng.uniform(-protocol.noise_pitch_deg, protocol.noise_pitch_deg)
        dy = rng.uniform(-protocol.noise_yaw_deg, protocol.noise_yaw_deg)
        out.append(Pose.from_body_rpy_deg(truth.translation + dt, rpy + [0.0, dp, dy]))
    return out


@dataclass
class Run:
    start: Pose
    pose: Pose
    loss: float
    translation_m: float
    rotation_deg: float
    seconds: float
    evaluations: int
    error: str = ""  # why the engine refused this start (then pose = start, loss = degenerate)
    quality: dict = field(default_factory=dict)  # the result's quality report (QualityReport.to_dict)

    def to_dict(self) -> dict:
        return {"start": pose_to_dict(self.start), "pose": pose_to_dict(self.pose),
                "loss": self.loss, "translation_error_m": self.translation_m,
                "rotation_error_deg": self.rotation_deg, "seconds": self.seconds,
                "evaluations": self.evaluations, "error": self.error, "quality": self.quality}

    @classmethod
    def from_dict(cls, d: dict) -> "Run":
        return cls(pose_from_dict(d["start"]), pose_from_dict(d["pose"]), float(d["loss"]),
                   float(d["translation_error_m"]), float(d["rotation_error_deg"]),
                   float(d["seconds"]), int(d["evaluations"]), str(d.get("error", "")),
                   dict(d.get("quality") or {}))


@dataclass
class SceneEvaluation:
    scene: str  # e.g. "junction/ideal seed 0"
    folder: str
    loss: str
    summary: Summary
    runs: list[Run] = field(default_factory=list)
    best: Pose | None = None  # the lowest-loss result (for overlays)
    prepare_seconds: float = 0.0  # preparing the map, once for all runs

    def to_dict(self) -> dict:
        return {"scene": self.scene, "folder": self.folder, "loss": self.loss,
                "summary": asdict(self.summary), "runs": [r.to_dict() for r in self.runs]}

    @classmethod
    def from_dict(cls, d: dict) -> "SceneEvaluation":
        """Back from :meth:`to_dict` (the ``--json`` output), e.g. to print a combined table."""
        try:
            runs = [Run.from_dict(r) for r in d["runs"]]
            out = cls(d["scene"], d["folder"], d["loss"], Summary(**d["summary"]), runs)
        except (KeyError, TypeError) as exc:
            raise ValueError(f"not an evaluation result: missing or bad field {exc}") from None
        out.best = min(runs, key=lambda r: r.loss).pose if runs else None
        return out


def scene_name(folder: Path) -> str:
    """``kind/variant seed N`` from scene.yaml, else the folder name."""
    meta_file = folder / "scene.yaml"
    if meta_file.is_file():
        meta = yaml.safe_load(meta_file.read_text()) or {}
        if {"kind", "variant", "seed"} <= set(meta):
            return f"{meta['kind']}/{meta['variant']} seed {meta['seed']}"
    return folder.name


def evaluate_scene(folder: str | Path, loss: str = "l2",
                   protocol: ProtocolParams = ProtocolParams(),
                   params: CalibrationParams | None = None, mapping: LabelMapping | None = None,
                   map_file: str | Path | None = None,
                   on_run: Callable[[int, Run], None] | None = None,
                   single: bool = False, label_noise: str = "",
                   noise_seed: int = 1) -> SceneEvaluation:
    """Run the protocol on one scene folder (map.ply, labels.png, camera_info.yaml,
    ground_truth.yaml); ``map_file`` replaces map.ply (e.g. a map built from noisy poses).
    ``label_noise`` names a model of :data:`semcal_tools.scenes.labelnoise.NOISE_MODELS` (or
    ``legacy``, the ``noisy_labels`` variant's) applied to labels.png with ``noise_seed``: the same
    scene with a network's kind of label errors.

    Each start runs the engine's full default procedure (verification starts included, seeded
    per start), as a user calling ``semcal calibrate`` would; ``single`` runs one schedule per
    start instead (no verification starts), the paper's single-run figure."""
    from semcal_ros.engine.search import solve
    from semcal_ros.engine.problem import Problem

    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"scene folder not found: {folder}")
    cloud = read_ply(Path(map_file) if map_file else folder / "map.ply")
    target = read_label_image(folder / "labels.png")
    probabilities = None  # the segmenter's softmax beside its labels (not with added noise)
    if (folder / "probabilities.npz").is_file() and not label_noise:
        from semcal_ros.engine.loss import read_probabilities

        probabilities = read_probabilities(folder / "probabilities.npz")
    if label_noise:
        from semcal_tools.scenes.labelnoise import noisy_labels

        target = noisy_labels(target, label_noise, noise_seed)
    camera = read_camera_info(folder / "camera_info.yaml")
    truth = read_pose(folder / "ground_truth.yaml")
    run_params = replace(params or CalibrationParams(),
                         loss=replace((params or CalibrationParams()).loss, kind=loss))
    if single:
        run_params = replace(run_params, verification=replace(run_params.verification, starts=0))
    starts = initial_guesses(truth, protocol)
    # one problem for all starts: the map is prepared once, cropped around the starts' mean
    t0 = time.perf_counter()
    problem = Problem(cloud, target, camera, np.mean([s.translation for s in starts], axis=0),
                      run_params, mapping, probabilities=probabilities)
    prepare_seconds = time.perf_counter() - t0
    runs = []
    for i, start in enumerate(starts):
        t0 = time.perf_counter()
        try:
            result = solve(problem, start, seed=protocol.seed + i)
            run = Run(start, result.pose, float(result.loss), translation_error(result.pose, truth),
                      rotation_error_deg(result.pose, truth), time.perf_counter() - t0,
                      int(result.evaluations),
                      quality=result.quality.to_dict() if result.quality else {})
        except ValueError as exc:  # the engine refused the start or its result: a failed run
            run = Run(start, start, run_params.loss.degenerate_loss,
                      translation_error(start, truth), rotation_error_deg(start, truth),
                      time.perf_counter() - t0, 0, str(exc))
        runs.append(run)
        if on_run is not None:
            on_run(i, run)
    summary = summarize(np.array([r.loss for r in runs]), np.array([r.translation_m for r in runs]),
                        np.array([r.rotation_deg for r in runs]), np.array([r.seconds for r in runs]),
                        protocol.keep, protocol.success_m, protocol.success_deg)
    best = min(runs, key=lambda r: r.loss).pose
    name = scene_name(folder) + (f", {label_noise} label noise" if label_noise else "")
    return SceneEvaluation(name, str(folder), loss, summary, runs, best,
                           prepare_seconds)


# -- the table ----------------------------------------------------------------------------------

#: Table I of the paper (mean of the 10 lowest-loss runs of 30), for comparison.
PAPER_TABLE_I = {
    "CARLA Town10HD": {"l2": (1.5, 0.03), "huber": (1.5, 0.02)},
    "CARLA Town01": {"l2": (6.0, 0.11), "huber": (6.2, 0.10)},
    "KITTI 00 semi-automatic": {"l2": (12.7, 0.28), "huber": (15.3, 0.26)},
    "KITTI 09 semi-automatic": {"l2": (20.6, 0.40), "huber": (19.3, 0.42)},
    "KITTI 00 automatic": {"l2": (20.2, 0.34), "huber": (20.3, 0.33)},
    "KITTI 09 automatic": {"l2": (18.6, 0.40), "huber": (19.6, 0.43)},
}


def _cell(t_cm: float, r_deg: float) -> str:
    return f"{t_cm:.1f} cm, {r_deg:.2f} deg"


def _verdicts(runs: list[Run]) -> str:
    """Share of runs the quality report called good, and in brackets the share of those that
    really were within the protocol's success bounds (5 cm / 0.1 deg)."""
    rated = [r for r in runs if r.quality]
    if not rated:
        return ""
    good = [r for r in rated if r.quality.get("verdict") == "good"]
    right = sum(r.translation_m < 0.05 and r.rotation_deg < 0.1 for r in good)
    return (f"{len(good) / len(rated) * 100:.0f} %"
            + (f" ({right / len(good) * 100:.0f} %)" if good else ""))


def format_table(results: list[SceneEvaluation], paper: bool = False) -> str:
    """A Markdown table shaped like the paper's Table I: one row per scene, a column per loss
    (mean of the kept lowest-loss runs), then all-run means, success rates and seconds per run."""
    losses = sorted({r.loss for r in results}, key=list(LOSS_KINDS).index)
    rows: dict[str, dict[str, SceneEvaluation]] = {}
    for r in results:
        rows.setdefault(r.scene, {})[r.loss] = r
    names = LOSS_KINDS
    head = ["scene", "kept of runs"] + [f"{names[k]} (kept)" for k in losses]
    head += [f"{names[k]} (all runs)" for k in losses]
    head += [f"{names[k]} success" for k in losses] + ["good (right)", "s/run"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene, by_loss in rows.items():
        sizes = sorted({(v.summary.keep, v.summary.runs) for v in by_loss.values()})
        cells = [scene, ", ".join(f"{k} of {n}" for k, n in sizes)]
        cells += [_cell(by_loss[k].summary.kept_translation_cm, by_loss[k].summary.kept_rotation_deg)
                  if k in by_loss else "" for k in losses]
        cells += [_cell(by_loss[k].summary.all_translation_cm, by_loss[k].summary.all_rotation_deg)
                  if k in by_loss else "" for k in losses]
        cells += [f"{by_loss[k].summary.success_rate * 100:.0f} %" if k in by_loss else ""
                  for k in losses]
        cells.append(_verdicts([run for v in by_loss.values() for run in v.runs]))
        secs = [v.summary.seconds_per_run for v in by_loss.values()]
        cells.append(f"{np.mean(secs):.1f}")
        lines.append("| " + " | ".join(cells) + " |")
    if paper:
        for scene, vals in PAPER_TABLE_I.items():
            cells = [f"paper: {scene}", "10 of 30"] + [_cell(*vals[k]) for k in losses]
            cells += [""] * (len(head) - len(cells))
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
