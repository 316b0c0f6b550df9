"""Which scene sections each computation reads: the section part of its fingerprint.

One definition, imported by the pipeline (stage cache keys), the FE reference
(per-experiment keys, ``reference.h5``'s ``scene_fingerprint``) and the
calibration (checkpoint key, ``params.h5`` settings). Free of dolfinx, so the
pipeline can use it without initialising MPI.
"""
from __future__ import annotations

#: sections every FE experiment reads (geometry, material, discretisation)
COMMON_SECTIONS = ("mesh", "material", "fixed", "test_points", "fe")
#: the sections each FE experiment reads besides :data:`COMMON_SECTIONS`
EXPERIMENT_SECTIONS = {"indentation": ("indentation",),
                       "relaxation": ("indentation", "relaxation"),  # the indenter
                       "gravity_static": ("gravity",),
                       "gravity_dynamic": ("gravity",),
                       "second_support": ("gravity", "second_support"),
                       # the loads are the scene's weight along the axes perpendicular to its
                       # gravity: the acceleration is read
                       "body": ("gravity", "body"),
                       # the gravity test, the second support's and the held-out points'
                       # curves on the particle mesh with the floor's own elements (fe.element
                       # and fe.refine are not used, the Newton settings are)
                       "floor": ("gravity", "second_support", "indentation", "relaxation")}
#: experiment -> the other experiments whose being asked for changes what it computes (part of
#: its key: the floor runs the second support's test only when the scene runs that test)
EXPERIMENT_OPTIONS = {"floor": ("second_support",)}
#: sections the whole FE reference reads (every experiment's)
REFERENCE_SECTIONS = ("mesh", "material", "fixed", "second_support", "test_points",
                      "indentation", "relaxation", "gravity", "body", "fe")
#: sections that set a calibration's fit (of ``[particle]`` only ``volume``, the model it fits,
#: which the calibration records separately); with gravity experiments it also reads
#: ``[gravity]`` and the rest of ``[particle]`` for its gravity check, which the pipeline's
#: calibrate stage adds to its cache key (``pipelines.stages``)
FIT_SECTIONS = ("mesh", "material", "fixed", "test_points", "indentation", "relaxation",
                "calibration")
