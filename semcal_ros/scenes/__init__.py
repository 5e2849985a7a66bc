"""Synthetic roadside scenes: labelled meshes seen by a ray-cast lidar and camera.

``generate_scene`` writes a scene folder in the format of docs/CONTRACTS.md; see docs/scenes.md.
"""

from semcal_ros.scenes.generate import SIZES, VARIANTS, SceneOptions, SceneResult, generate_scene
from semcal_ros.scenes.layouts import KINDS

__all__ = ["KINDS", "SIZES", "VARIANTS", "SceneOptions", "SceneResult", "generate_scene"]
