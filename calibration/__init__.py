"""Calibration of the particle model's connector parameters against the FE reference.

``calibrate(scene, reference_path, out_path)`` fits them and writes ``params.h5``;
``read_params(path)`` reads it back; ``relative_rms_error(sim, ref)`` is the error
figure quoted everywhere. ``python -m calibration --help`` is the command line.
"""
import forcecal  # noqa: F401  (settles the numba cache folder before numba is imported: forcecal.caches)
from calibration.core import calibrate
from calibration.metrics import relative_rms_error
from calibration.results import CalibrationResult, read_params

__all__ = ["calibrate", "read_params", "relative_rms_error", "CalibrationResult"]
