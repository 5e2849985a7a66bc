"""What a calibration returns: the result, each start's run, the quality report, progress.

Plain data, in a module of its own so that the search, the quality report, the drift check, the
nodes and the command line share them without importing each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from semcal_ros.engine.pose import Pose


@dataclass(frozen=True)
class Progress:
    stage: str
    evaluations: int
    best_loss: float  # best of the running stage (losses of different resolutions differ)
    best_pose: Pose


@dataclass(frozen=True)
class RunResult:
    """One start: where its coarse stage ended, and the full schedule's result if refined."""

    start: Pose
    pose: Pose  # refined pose, or the coarse one when the start was not refined
    loss: float  # full-resolution loss when refined, else the coarse loss
    evaluations: int
    coarse_loss: float
    refined: bool
    basin: int  # index of the basin (0 = the one of the result)


@dataclass(frozen=True)
class ClassEvidence:
    """What one class of the labels says at the result: which of the map's classes to trust.
    An unfamiliar lidar's point labels fail by class (facades called vegetation, the road's
    edge called terrain): a class the map covers but disagrees on pulls the pose wherever its
    mislabelled points lie."""

    name: str  # Cityscapes name
    share: float  # of the labelled pixels the loss judges (sky aside)
    coverage: float  # of the class's pixels, those a map point covers
    agreement: float  # of those covered, those the map labels the same

    def to_dict(self) -> dict:
        return {"class": self.name, "share": round(self.share, 4),
                "coverage": round(self.coverage, 4), "agreement": round(self.agreement, 4)}


@dataclass(frozen=True)
class QualityReport:
    verdict: str  # "good" | "inconclusive" | "failed"
    reason: str  # one line: why (names the axis or the measure at fault)
    agreement: float
    agreement_per_class: dict[str, float]
    coverage: float
    uncertainty_translation_m: tuple[float, float, float]  # map x, y, z
    uncertainty_rpy_deg: tuple[float, float, float]  # camera body roll, pitch, yaw
    unconstrained: tuple[str, ...] = ()  # axes whose uncertainty is above the thresholds
    spread_translation_m: float = 0.0
    spread_rotation_deg: float = 0.0
    evaluations: int = 0  # loss evaluations the report cost
    roll_free: bool = False  # roll searched (else held fixed, and its uncertainty not judged)
    # the result's distance from its start (m per map axis, pitch deg, yaw deg; None: no start
    # given) and whether that lies beyond the measured basin (quality.basin_*)
    start_offset: tuple[float, float, float] | None = None
    start_outside_basin: bool = False
    # how the uncertainty was measured: "loss rise" (the probes), or the independent evidence's
    # method (engine/evidence.py) with its per-axis sigma and largest move (x y z m, r p y deg)
    uncertainty_method: str = "loss rise"
    evidence_sigma: tuple[float, ...] = ()
    evidence_moves: tuple[float, ...] = ()
    # per class of the labels, largest first (engine.quality.class_evidence)
    classes: tuple[ClassEvidence, ...] = ()

    def to_dict(self) -> dict:
        """The ``quality:`` group of a result YAML."""
        return {
            "verdict": self.verdict,
            "reason": self.reason,
            "agreement": round(float(self.agreement), 4),
            "agreement_per_class": {k: round(float(v), 4)
                                    for k, v in self.agreement_per_class.items()},
            "coverage": round(float(self.coverage), 4),
            "classes": [c.to_dict() for c in self.classes],
            "uncertainty_translation_m": [round(float(v), 4)
                                          for v in self.uncertainty_translation_m],
            "uncertainty_rpy_deg": [round(float(v), 4) for v in self.uncertainty_rpy_deg],
            "unconstrained": list(self.unconstrained),
            "spread_translation_m": round(float(self.spread_translation_m), 4),
            "spread_rotation_deg": round(float(self.spread_rotation_deg), 4),
            "uncertainty_method": self.uncertainty_method,
            **({"start_offset": {"translation_m": round(self.start_offset[0], 3),
                                 "pitch_deg": round(self.start_offset[1], 3),
                                 "yaw_deg": round(self.start_offset[2], 3)},
                "start_outside_basin": bool(self.start_outside_basin)}
               if self.start_offset is not None else {}),
        }

    def classes_line(self, min_share: float = 0.01, trusted: float = 0.5) -> str:
        """The classes of at least ``min_share`` of the labels, largest first: how much of each
        the map covers and how much of that agrees; those agreeing on less than ``trusted``
        named apart (the map's labels of that class are not what the camera's segmenter
        sees)."""
        shown = [c for c in self.classes if c.share >= min_share]
        if not shown:
            return "classes: none covered"
        cells = [f"{c.name} {c.agreement * 100:.0f} % ({c.coverage * 100:.0f} % covered)"
                 for c in shown]
        low = [c.name for c in shown if c.coverage > 0 and c.agreement < trusted]
        line = "classes, agree (covered): " + ", ".join(cells)
        if low:
            line += (f"; disagree on most of their pixels here: {', '.join(low)} (at a right "
                     "pose: the map's labels of these are not what the camera's segmenter "
                     "sees)")
        return line

    def summary(self) -> str:
        """One line for logs and the overlay."""
        ut = self.uncertainty_translation_m
        ur = self.uncertainty_rpy_deg if self.roll_free else self.uncertainty_rpy_deg[1:]
        return (f"{self.verdict.upper()}: {self.reason}; agreement {self.agreement * 100:.0f} %, "
                f"coverage {self.coverage * 100:.0f} %, +- {max(ut) * 100:.1f} cm / "
                f"{max(ur):.2f} deg")


@dataclass
class CalibrationResult:
    pose: Pose
    loss: float
    evaluations: int
    seconds: float
    history: list[tuple[int, int, float]] = field(default_factory=list)  # (run, stage, loss)
    runs: list[RunResult] = field(default_factory=list)
    accepted: int = 1  # starts that ended in the result's basin
    quality: QualityReport | None = None  # how good, without ground truth (semcal_ros.engine.quality)

    # One home per fact: the quality report measured these; the result refers to it (0 without
    # a report).
    @property
    def spread_translation_m(self) -> float:
        """RMS distance of the agreeing starts' poses from the result (m)."""
        return self.quality.spread_translation_m if self.quality is not None else 0.0

    @property
    def spread_rotation_deg(self) -> float:
        """RMS angle of the agreeing starts' poses from the result (deg)."""
        return self.quality.spread_rotation_deg if self.quality is not None else 0.0

    @property
    def coverage(self) -> float:
        """Share of the target's non-sky pixels the map covers at the result."""
        return self.quality.coverage if self.quality is not None else 0.0

    def to_dict(self) -> dict:
        """The fields a result pose YAML adds to the pose itself."""
        return {
            "loss": float(self.loss),
            "evaluations": int(self.evaluations),
            "seconds": round(float(self.seconds), 3),
            "rpy_deg": [float(v) for v in self.pose.body_rpy_deg()],
            "coverage": round(float(self.coverage), 4),
            "verification": {
                "runs": len(self.runs),
                "refined": sum(r.refined for r in self.runs),
                "accepted": int(self.accepted),
                "spread_translation_m": float(self.spread_translation_m),
                "spread_rotation_deg": float(self.spread_rotation_deg),
            },
            **({"quality": self.quality.to_dict()} if self.quality is not None else {}),
        }
