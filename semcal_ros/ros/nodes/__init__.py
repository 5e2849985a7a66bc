"""ROS 2 nodes, one module each with ``main()`` (console scripts in setup.py)."""
