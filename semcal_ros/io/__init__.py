"""File formats: labelled PLY maps, pose and camera_info YAML, label images, KITTI layouts."""
