"""Synthetic roadside scenes: labelled meshes seen by a ray-cast lidar and camera.

``generate_scene`` writes a scene folder in the format of docs/CONTRACTS.md; ``catalogue()``
lists the scenes of the engine's evaluation table; see docs/scenes.md.
"""

from semcal_tools.scenes.catalogue import CatalogueScene, catalogue
from semcal_tools.scenes.generate import (
    MAP_FRAMES, MASTS, SIZES, VARIANTS, MapFrame, SceneOptions, SceneResult, generate_scene,
)
from semcal_tools.scenes.layouts import KINDS

__all__ = ["KINDS", "MAP_FRAMES", "MASTS", "SIZES", "VARIANTS", "CatalogueScene", "MapFrame",
           "SceneOptions", "SceneResult", "catalogue", "generate_scene"]
