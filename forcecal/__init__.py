"""forcecal: calibrate real-time particle models of soft tissue against an FE reference.

This package holds the data contracts shared by every part of the project:
scenes (:mod:`forcecal.scene`), tetrahedral meshes (:mod:`forcecal.mesh`) and
the HDF5 files exchanged between the FE side and the particle side
(:mod:`forcecal.h5io`). It depends on numpy/scipy/h5py/meshio only (gmsh is
imported lazily to generate the default organ); dolfinx lives in
``reference_fe`` alone.
"""

__version__ = "0.1.0"

#: the project's top-level packages (their loggers, their code in the stage cache keys)
PROJECT_PACKAGES = ("forcecal", "reference_fe", "particle", "calibration", "pipelines")

from forcecal.caches import settle_caches as _settle_caches

# before any project module imports numba or dolfinx: a shared cache another user id filled
# is unusable to this one
_settle_caches()
