"""semcal_ros: target-free extrinsic camera calibration against a semantically labelled lidar map."""

__version__ = "0.1.0"
