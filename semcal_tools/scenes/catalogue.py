"""The scenes the engine's evaluation table covers: every layout x condition, named and seeded.

Users' scenes differ from a generator's defaults in ways that matter to a calibration: the map
frame is wherever their mapper started, the camera's own mast and housing are in the map, maps
run to millions of points, lidars have 32-128 lines. The catalogue's scenes carry all of that by
default (``user_like=True``: random map frame, camera housing on the mast); ``user_like=False``
gives the same worlds in the layout frame with the plain mast, the scenes of the earlier
docs/scenes.md table (same kind, seed and variant make the same scene as before).

Each entry is one ``semcal scene`` command (:meth:`CatalogueScene.command`) or one call
(:meth:`CatalogueScene.generate`); ``semcal scene --list`` prints them all.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from semcal_tools.scenes.generate import NOISY_POSE_MAP, SIZES, SceneOptions, SceneResult, generate_scene

#: Layouts in table order.
TABLE_KINDS = ("junction", "arterial", "roundabout", "highway")
#: Table rows per layout: (row name, variant, size, lidar lines). ``sparse`` is the 32-line lidar.
ROWS = (
    ("ideal", "ideal", "full", None),
    ("noisy_labels", "noisy_labels", "full", None),
    ("dynamic", "dynamic", "full", None),
    ("sparse", "sparse", "full", None),
    ("lines64", "ideal", "full", 64),
    ("large", "ideal", "large", None),
)
#: Map voxel of the ``large`` row where 5 cm stays under 3 M points (seed 0 at 5 cm: junction
#: 3.80 M, arterial 3.05 M, roundabout 2.42 M, highway 1.46 M).
LARGE_VOXEL = {"roundabout": 0.04, "highway": 0.03}


@dataclass(frozen=True)
class CatalogueScene:
    """One scene of the evaluation table."""

    name: str  # folder name, "<kind>-<row>"
    kind: str
    variant: str
    seed: int = 0
    size: str = "full"
    lines: int | None = None
    map_frame: str = "random"
    mast: str = "bracket"
    voxel: float | None = None  # map voxel, metres (None: the size's)

    @property
    def map_file(self) -> str:
        """The map the evaluation should calibrate against (pose_noise: the blurred one)."""
        return NOISY_POSE_MAP if self.variant == "pose_noise" else "map.ply"

    def options(self, bag: bool = False, scans: bool = False) -> SceneOptions:
        """Generator options; without bag and scan files (the evaluation reads neither)."""
        changes = {"map_frame": self.map_frame, "mast": self.mast, "write_bag": bag,
                   "write_scans": scans}
        if self.lines is not None:
            changes["lines"] = self.lines
        if self.voxel is not None:
            changes["voxel"] = self.voxel
        return replace(SIZES[self.size], **changes)

    def command(self, root: str | Path = "scenes") -> str:
        """The ``semcal scene`` command line that makes this scene in ``root/<name>``."""
        parts = ["semcal scene", f"--kind {self.kind}", f"--variant {self.variant}",
                 f"--seed {self.seed}", f"--size {self.size}"]
        if self.lines is not None:
            parts.append(f"--lines {self.lines}")
        if self.voxel is not None:
            parts.append(f"--voxel {self.voxel:g}")
        parts += [f"--frame {self.map_frame}", f"--mast {self.mast}", "--no-bag", "--no-scans",
                  f"--out {Path(root) / self.name}"]
        return " ".join(parts)

    def generate(self, root: str | Path, force: bool = False, progress: bool = False
                 ) -> SceneResult:
        return generate_scene(Path(root) / self.name, self.kind, self.seed, self.variant,
                              self.options(), force=force, progress=progress)


def catalogue(seed: int = 0, user_like: bool = True, kinds: tuple[str, ...] = TABLE_KINDS,
              rows: tuple[str, ...] | None = None, pose_noise: bool = True
              ) -> list[CatalogueScene]:
    """The evaluation table's scenes: ``kinds`` x ``rows`` (all of :data:`ROWS` by default),
    plus the junction's pose_noise scene (map built from perturbed poses) with ``pose_noise``."""
    frame, mast = ("random", "bracket") if user_like else ("layout", "pole")
    wanted = rows or tuple(r[0] for r in ROWS)
    unknown = set(wanted) - {r[0] for r in ROWS}
    if unknown:
        raise ValueError(f"unknown catalogue row(s) {', '.join(sorted(unknown))} "
                         f"(choose from {', '.join(r[0] for r in ROWS)})")
    out = [CatalogueScene(f"{kind}-{row}", kind, variant, seed, size, lines, frame, mast,
                          LARGE_VOXEL.get(kind) if row == "large" else None)
           for kind in kinds for row, variant, size, lines in ROWS if row in wanted]
    if pose_noise and "junction" in kinds:
        out.append(CatalogueScene("junction-pose_noise", "junction", "pose_noise", seed,
                                  map_frame=frame, mast=mast))
    return out


def find(name: str, seed: int = 0, user_like: bool = True) -> CatalogueScene:
    """The catalogue entry called ``name`` (e.g. ``roundabout-sparse``)."""
    entries = {e.name: e for e in catalogue(seed, user_like)}
    if name not in entries:
        raise ValueError(f"no catalogue scene '{name}' (choose from {', '.join(entries)})")
    return entries[name]
