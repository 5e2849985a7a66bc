"""Calibration parameters: one dataclass tree, filled from ``config/calibrator.yaml``.

Defaults reproduce the paper's search (+-2.5 m, +-5 deg, roll fixed, Nelder-Mead restarted with
tolerances 1e-4, 1e-4, 1e-6) on a coarse-to-fine schedule that makes one calibration take about a
second on a 1M-point map.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from semcal_ros.loss import LossParams


@dataclass(frozen=True)
class RenderParams:
    splat_lambda: float = 0.0  # disc radius px = splat_lambda / distance m; 0 = from the map
    splat_scale: float = 1.5  # with splat_lambda 0: disc radius = splat_scale x point spacing
    radius_max: float = 8.0  # px, full resolution
    depth_falloff: float = 0.3  # depth factor at a disc's rim: nearest centre wins within a surface
    depth_falloff_coarse: float = 0.05  # the same for reduced-resolution stages (smoother basin)
    core_fraction: float = 1.0  # share of the disc radius that carries the label (rim: depth only)
    near: float = 0.5  # m
    far: float = 150.0  # m
    crop_radius: float = 120.0  # m around the initial camera position; 0 keeps the whole map


    def splat_lambda_for(self, point_spacing_m: float, focal_px: float) -> float:
        """The disc size: given, or one that closes the gaps between neighbouring points.

        The paper tuned lambda by eye until a rendered view looked as dense as the target; a
        disc of ``splat_scale`` times the map's median nearest-neighbour gap does that for any
        map and camera (lidar maps are anisotropic, so the gap between scan lines is larger than
        that median); much larger discs overshoot outlines and bias the pose.
        """
        if self.splat_lambda > 0:
            return self.splat_lambda
        return self.splat_scale * focal_px * max(point_spacing_m, 1e-3)


@dataclass(frozen=True)
class SearchParams:
    bound_xyz: tuple[float, float, float] = (2.5, 2.5, 2.5)  # m
    bound_roll_deg: float = 2.0  # only searched with free_roll
    bound_pitch_deg: float = 5.0
    bound_yaw_deg: float = 5.0
    free_roll: bool = False
    yaw_search: bool = False  # coarse grid over the full circle first (yaw not known at all)
    yaw_search_step_deg: float = 10.0
    yaw_search_keep: int = 3

    def __post_init__(self) -> None:
        values = (*self.bound_xyz, self.bound_pitch_deg, self.bound_yaw_deg)
        if len(self.bound_xyz) != 3 or min(values) <= 0 or (self.free_roll and self.bound_roll_deg <= 0):
            raise ValueError("search bounds must be positive (bound_xyz has 3 values)")


@dataclass(frozen=True)
class ScheduleParams:
    """Nelder-Mead stages, coarse to fine; all tuples have one entry per stage."""

    scales: tuple[int, ...] = (4, 2, 1)  # image downscale factor
    point_fractions: tuple[float, ...] = (0.125, 0.5, 1.0)  # share of map points rendered
    simplex: tuple[float, ...] = (1.0, 0.1, 0.03)  # initial simplex, as a fraction of the bounds
    fatol: tuple[float, ...] = (1e-4, 1e-4, 1e-6)  # the paper's tolerances, on the mean loss
    max_evaluations: tuple[int, ...] = (500, 200, 150)
    xatol: float = 1e-3  # in units of the bounds
    final_restarts: int = 2  # the last stage again from its result while that lowers the loss

    def __post_init__(self) -> None:
        n = len(self.scales)
        if n == 0 or any(len(t) != n for t in (self.point_fractions, self.simplex, self.fatol,
                                                self.max_evaluations)):
            raise ValueError("schedule tuples must all have one entry per stage")


@dataclass(frozen=True)
class VerificationParams:
    starts: int = 10  # extra runs from noisy initial guesses
    noise: float = 0.5  # uniform noise of the starts, as a fraction of the search bounds
    loss_margin: float = 0.05  # a run is accepted when its loss <= best * (1 + margin) + abs
    loss_margin_abs: float = 1e-4  # (a purely relative margin rejects everything near loss 0)


@dataclass(frozen=True)
class CalibrationParams:
    render: RenderParams = field(default_factory=RenderParams)
    loss: LossParams = field(default_factory=LossParams)
    search: SearchParams = field(default_factory=SearchParams)
    schedule: ScheduleParams = field(default_factory=ScheduleParams)
    verification: VerificationParams = field(default_factory=VerificationParams)
