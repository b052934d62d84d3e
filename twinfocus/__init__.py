"""TwinFocus: twin-reference autofocus for handheld 77 GHz MIMO-SAR imaging.

The numerics live in small modules named after what they hold: ``radar`` (chirp, MIMO
array, range compression), ``scan``, ``trajectory``, ``motion``, ``scene``, ``simulate``,
``grid``, ``backprojection``, ``autofocus``, ``metrics``. No sockets and no processes here.
"""

import os

# numba picks its threading layer at the first parallel kernel, TBB first by default; open3d (the
# digital twin's point clouds) loads its own TBB, older than numba accepts, and numba then warns on
# every run before falling back to OpenMP. OpenMP first: the same layer, without the warning.
os.environ.setdefault("NUMBA_THREADING_LAYER_PRIORITY", "omp tbb workqueue")

__version__ = "0.1.0"
