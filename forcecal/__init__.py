"""forcecal: calibrate real-time particle models of soft tissue against an FE reference.

This package holds the data contracts shared by every part of the project:
scenes (:mod:`forcecal.scene`), tetrahedral meshes (:mod:`forcecal.mesh`; the generated
liver in :mod:`forcecal.liver_mesh`, the fixed nodes and test points in
:mod:`forcecal.point_selection`) and the HDF5 files exchanged between the FE side and the
particle side (:mod:`forcecal.h5io`). It depends on numpy/scipy/h5py/meshio only (gmsh is
imported lazily to generate the default organ); dolfinx lives in ``reference_fe`` alone.

``forcecal.load_model(path)`` loads a calibrated particle model from its ``params.h5``
(:func:`calibration.loading.load_model`; ``load_calibrated`` returns it with its mesh, test
points and valid strain range). Both are imported on first use, so importing
:mod:`forcecal` stays light.
"""

__version__ = "0.1.0"

#: the project's top-level packages (their loggers, their code in the stage cache keys)
PROJECT_PACKAGES = ("forcecal", "reference_fe", "particle", "calibration", "pipelines")

from forcecal.caches import settle_caches as _settle_caches

# before any project module imports numba or dolfinx: a shared cache another user id filled
# is unusable to this one
_settle_caches()


#: names this package lends from the layers above it, imported on first use
_LAZY = {"load_model": "calibration.loading", "load_calibrated": "calibration.loading"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'forcecal' has no attribute {name!r}")
