"""Z-buffer splat rendering of a labelled map into a label image.

Two implementations with one signature and pixel-identical output: ``reference`` (pure numpy, the
readable definition) and ``fast`` (numba, two threads, chunk culling; what the optimiser calls).
"""

from semcal_ros.engine.render.prepare import PreparedMap, prepare_map
from semcal_ros.engine.render.view import View, ViewSetup, make_view, view_for, view_setup

__all__ = ["PreparedMap", "View", "ViewSetup", "make_view", "prepare_map",
           "view_for", "view_setup"]

