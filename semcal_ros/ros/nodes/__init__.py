"""ROS 2 nodes, one module each with ``main()`` (console scripts in setup.py).

OpenBLAS starts one spinning thread per core for every matrix product, even (N, 3) x (3, 3) ones;
with several nodes sharing a few cores that made such products ~100x slower. Nodes therefore
default to one BLAS thread (set OPENBLAS_NUM_THREADS to change it); this runs before any node
module imports numpy.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
