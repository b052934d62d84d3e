"""Back-projection: the exact matched filter of the IF model, two back-ends side by side.

:mod:`~twinfocus.imaging.backprojection.numba_backend` (CPU, numba) holds the entry functions
(``backproject``, ``backproject_points``, ``subimage_basis``, ``subimage_basis_points``);
``backproject_points(..., device=...)`` hands a torch device to
:mod:`~twinfocus.imaging.backprojection.torch_backend` (CUDA, also CPU).
"""
