"""Map building: scans and poses into one labelled map (the paper's step 1), without ROS."""

from semcal_ros.mapping.builder import (
    MapBuildParams, MapBuildResult, ScanInput, ScanRejected, ScanReport, StreamingMapBuilder,
    build_map)
from semcal_ros.mapping.registration import RegistrationParams

__all__ = ["MapBuildParams", "MapBuildResult", "RegistrationParams", "ScanInput", "ScanRejected",
           "ScanReport", "StreamingMapBuilder", "build_map"]
