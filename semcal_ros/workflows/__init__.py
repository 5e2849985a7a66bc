"""Workflows: what a command or a node does with the engine, mapping, segmentation and file
formats, without ROS. The CLI (``semcal_ros/cli``) and the nodes (``semcal_ros/ros/nodes``) are
thin adapters that call these, as both call :func:`semcal_ros.engine.overlay.calibrate_and_draw`.

* :mod:`.real_scene`, :mod:`.kitti_scene`: a recording (image, scans, calibration) as a scene
  folder; :mod:`.scene_labels`: the point labels and label images they need;
* :mod:`.live_map`: the live map's worker (scan queue, time jumps, work clock) that
  ``map_builder`` wires to its topics.
"""
