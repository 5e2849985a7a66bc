"""Test and demo tooling beside the product: synthetic scenes, the synthetic street, the
benchmark, the paper's evaluation protocol, the live demo and the ROS launch helpers.

Registers its ``semcal`` sub-commands (scene, bench, evaluate, demo) through
``semcal_tools.cli``; nothing in ``semcal_ros`` imports from here except the command's
sub-command discovery.
"""
