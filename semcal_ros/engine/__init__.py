"""The calibration engine: everything between a labelled map, a label image and a pose.

ROS-free and free of test tooling (``semcal_tools``). Where things live:

- ``camera`` (lens models, projection), ``pose`` (poses and their errors), ``labels`` (class
  sets and alignment), ``cloud`` (the labelled point cloud);
- ``render/`` (the labelled map drawn into a label image: ``reference`` defines it, ``fast`` runs);
- ``loss`` (rendered vs observed labels), ``problem`` (a map, a camera and a target image as one
  function of the pose), ``search`` (the paper's schedule of Nelder-Mead stages, restarts,
  verification), ``quality`` (the verdict), ``drift`` (the cheap re-check of a held pose);
- ``params`` / ``config`` / ``validation`` (every setting, read from the ROS-style YAML, checked
  all at once), ``overlay`` (the picture of a result).
"""
