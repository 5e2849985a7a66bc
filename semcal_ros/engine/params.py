"""Engine parameters: one dataclass tree, the ``engine:`` group of ``config/calibrator.yaml``.

The calibrator node reads this tree under the ``engine.`` prefix (as the map builder reads its
``mapping.`` group) and ``semcal calibrate --config`` / ``semcal evaluate --config`` read the same
group from the same file (:meth:`CalibrationParams.from_file`), so one parameter file gives the
same result through either door. Defaults reproduce the paper's search (+-2.5 m, +-5 deg, roll
fixed, Nelder-Mead restarted with tolerances 1e-4, 1e-4, 1e-6, verification from perturbed starts)
on a coarse-to-fine schedule; docs/engine.md says what each value buys, measured.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path

from semcal_ros.engine.config import apply_flat, check_finite, check_rule, load_node_params
from semcal_ros.engine.cues import CueParams
from semcal_ros.engine.loss import LossParams
from semcal_ros.engine.quality import QualityParams
from semcal_ros.engine.render.view import RenderParams

#: Beyond these the search is no calibration any more (the loss has no basin that wide).
MAX_BOUND_XYZ_M = 50.0
MAX_BOUND_DEG = 180.0


@dataclass(frozen=True)
class LabelParams:
    """Class alignment changes beyond the built-in SemanticKITTI -> Cityscapes table."""

    merge: tuple[str, ...] = ()  # "from:to" Cityscapes class names merged in both domains
    # (the paper on KITTI: ["sidewalk:road"])
    parked_vehicles: bool = False  # vehicles count (parked cars in map and image); moving-* dropped

    def __post_init__(self) -> None:
        for item in self.merge:
            if item.count(":") != 1 or not all(item.split(":")):
                raise ValueError(f"labels.merge entries are 'from:to' class names, got '{item}'")

    def as_dict(self) -> dict[str, str]:
        return dict(item.split(":") for item in self.merge)


@dataclass(frozen=True)
class SearchParams:
    bound_xyz: tuple[float, float, float] = (2.5, 2.5, 2.5)  # m
    bound_roll_deg: float = 2.0  # only searched with free_roll
    bound_pitch_deg: float = 5.0
    bound_yaw_deg: float = 5.0
    free_roll: bool = False
    yaw_search: bool = False  # coarse grid over the full circle first (yaw not known at all)
    yaw_search_step_deg: float = 10.0
    yaw_search_probe: int = 16  # best-scored headings that get a short coarse descent
    yaw_search_probe_evaluations: int = 100  # length of that descent
    yaw_search_keep: int = 3  # lowest after the descent: starts of the search
    yaw_search_confine: float = 1.5  # with the yaw search, x/y/z/pitch stay within this many
    # bounds of the initial guess (0: unconfined)
    yaw_search_coverage_weight: float = 0.2  # with the yaw search, + this x uncovered share

    def __post_init__(self) -> None:
        check_finite(self)
        if len(self.bound_xyz) != 3:
            raise ValueError(f"search.bound_xyz needs 3 values, got {len(self.bound_xyz)}")
        angles = (self.bound_pitch_deg, self.bound_yaw_deg) + \
            ((self.bound_roll_deg,) if self.free_roll else ())
        if min(*self.bound_xyz, *angles) <= 0:
            raise ValueError("search bounds must be positive")
        if max(self.bound_xyz) > MAX_BOUND_XYZ_M:
            raise ValueError(f"search.bound_xyz {max(self.bound_xyz):g} m is beyond what the "
                             f"method can search (at most {MAX_BOUND_XYZ_M:g} m): give a better "
                             "initial position")
        if max(angles) > MAX_BOUND_DEG:
            raise ValueError(f"search angle bound {max(angles):g} deg is beyond "
                             f"{MAX_BOUND_DEG:g} deg (use search.yaw_search for an unknown yaw)")
        check_rule("search.yaw_search_step_deg", self.yaw_search_step_deg,
               0 < self.yaw_search_step_deg <= 90, "in (0, 90]")
        check_rule("search.yaw_search_keep", self.yaw_search_keep, self.yaw_search_keep >= 1, ">= 1")
        check_rule("search.yaw_search_probe", self.yaw_search_probe,
                   self.yaw_search_probe >= self.yaw_search_keep, ">= yaw_search_keep")
        check_rule("search.yaw_search_probe_evaluations", self.yaw_search_probe_evaluations,
                   self.yaw_search_probe_evaluations >= 1, ">= 1")
        check_rule("search.yaw_search_coverage_weight", self.yaw_search_coverage_weight,
                   self.yaw_search_coverage_weight >= 0, ">= 0")
        check_rule("search.yaw_search_confine", self.yaw_search_confine,
                   self.yaw_search_confine == 0 or self.yaw_search_confine >= 1, "0 or >= 1")


@dataclass(frozen=True)
class Stage:
    """One Nelder-Mead stage of the schedule."""

    scale: int  # image downscale factor (1 = full resolution)
    simplex: float  # initial simplex, as a fraction of the search bounds
    fatol: float  # loss change that ends the stage (the loss is a mean over valid pixels)
    max_evaluations: int  # cap of the stage
    restarts: int  # the stage again from its own result while that lowers the loss


@dataclass(frozen=True)
class ScheduleParams:
    """Nelder-Mead stages, coarse to fine, one entry per stage in each list.

    Kept as parallel lists because ROS parameters are flat typed arrays; the engine only ever
    sees :meth:`stages`.
    """

    scales: tuple[int, ...] = (4, 2, 1)
    simplex: tuple[float, ...] = (1.0, 0.1, 0.03)
    fatol: tuple[float, ...] = (1e-4, 1e-4, 1e-6)  # the paper's tolerances
    max_evaluations: tuple[int, ...] = (300, 150, 80)
    # the paper's restarts from the previous result, per stage; the first stage's run only for
    # the basins chosen for refinement (a coarse Nelder-Mead often stops before the bottom)
    restarts: tuple[int, ...] = (1, 0, 1)
    xatol: float = 1e-3  # in units of the bounds
    # a stage ends once its best loss has not dropped by more than its fatol for this many
    # evaluations (the loss is piecewise constant: plateaus, not the tolerance, end a stage); 0 = off
    stall_evaluations: int = 0
    # several frames of one rig: the first stage searches this many of them, spread evenly over
    # the set, the later stages all (0: all). The first stage only finds the basins
    coarse_frames: int = 3

    def __post_init__(self) -> None:
        check_finite(self)
        n = len(self.scales)
        if n == 0 or any(len(t) != n for t in (self.simplex, self.fatol, self.max_evaluations,
                                                self.restarts)):
            raise ValueError("schedule: scales, simplex, fatol, max_evaluations and restarts "
                             "need one entry per stage each")
        check_rule("schedule.scales", self.scales, min(self.scales) >= 1, ">= 1")
        check_rule("schedule.simplex", self.simplex, min(self.simplex) > 0, "> 0")
        check_rule("schedule.fatol", self.fatol, min(self.fatol) >= 0, ">= 0")
        check_rule("schedule.max_evaluations", self.max_evaluations, min(self.max_evaluations) >= 1,
               ">= 1")
        check_rule("schedule.restarts", self.restarts, min(self.restarts) >= 0, ">= 0")
        check_rule("schedule.xatol", self.xatol, self.xatol > 0, "> 0")
        check_rule("schedule.stall_evaluations", self.stall_evaluations,
                   self.stall_evaluations >= 0, ">= 0")
        check_rule("schedule.coarse_frames", self.coarse_frames, self.coarse_frames >= 0,
                   ">= 0")
        if self.scales[-1] != 1:
            raise ValueError("schedule: the last stage must be at full resolution (scale 1)")

    def stages(self) -> tuple[Stage, ...]:
        return tuple(Stage(int(s), float(x), float(f), int(m), int(r)) for s, x, f, m, r in
                     zip(self.scales, self.simplex, self.fatol, self.max_evaluations,
                         self.restarts))


@dataclass(frozen=True)
class VerificationParams:
    """The paper's verification: more starts around the initial guess; the lowest loss wins.

    Every start runs the first (coarse) stage only; starts that end in the same place are merged,
    and only the best and the distinct basins within ``refine_margin`` of its coarse loss are
    refined at full resolution (at most ``refine_max``): full-resolution renders are spent only
    where they can change the answer.
    """

    starts: int = 6  # extra starts besides the initial guess
    noise: float = 1.0  # uniform noise of the starts, as a fraction of the bounds (> 1 acts as 1:
    # the search stays within the bounds of its start)
    refine_margin: float = 0.2  # coarse loss <= best * (1 + margin): worth refining
    refine_max: int = 3  # at most this many basins refined at full resolution
    # of those, this many (the best at the stage before the last) run the last, full-resolution
    # stage at once; the others only if their full-resolution loss comes near (0: every one)
    refine_final: int = 1
    merge_translation_m: float = 0.3  # coarse results closer than this and
    merge_rotation_deg: float = 0.3  # this are one basin
    loss_margin: float = 0.05  # refined runs with loss <= best * (1 + margin) + abs agree
    loss_margin_abs: float = 1e-4

    def __post_init__(self) -> None:
        check_finite(self)
        for name in ("starts", "noise", "refine_margin", "merge_translation_m",
                     "merge_rotation_deg", "loss_margin", "loss_margin_abs"):
            check_rule(f"verification.{name}", getattr(self, name), getattr(self, name) >= 0, ">= 0")
        check_rule("verification.refine_max", self.refine_max, self.refine_max >= 1, ">= 1")
        check_rule("verification.refine_final", self.refine_final, self.refine_final >= 0,
                   ">= 0")


@dataclass(frozen=True)
class CalibrationParams:
    render: RenderParams = field(default_factory=RenderParams)
    loss: LossParams = field(default_factory=LossParams)
    labels: LabelParams = field(default_factory=LabelParams)
    search: SearchParams = field(default_factory=SearchParams)
    schedule: ScheduleParams = field(default_factory=ScheduleParams)
    verification: VerificationParams = field(default_factory=VerificationParams)
    quality: QualityParams = field(default_factory=QualityParams)
    cues: CueParams = field(default_factory=CueParams)  # terms beside the labels (engine/cues.py)

    @classmethod
    def from_file(cls, path: str | Path | None, node: str = "calibrator",
                  base: "CalibrationParams | None" = None) -> "CalibrationParams":
        """The ``engine:`` group of a ROS 2 parameter file (the calibrator node's own
        parameters beside it are not the engine's and are skipped); an unknown name inside the
        group is an error naming it, so a typo never passes silently."""
        params = base or cls()
        if path is None:
            return params
        prefix = "engine."
        every = load_node_params(path, node)
        groups = {f.name for f in fields(cls)}
        stray = sorted({k.split(".", 1)[0] for k in every if k.split(".", 1)[0] in groups})
        if stray:
            raise ValueError(f"{path}: engine parameter group(s) {', '.join(stray)} must stand "
                             "under 'engine:' (see config/calibrator.yaml)")
        flat = {k[len(prefix):]: v for k, v in every.items() if k.startswith(prefix)}
        try:
            return apply_flat(params, flat, strict=True)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None

