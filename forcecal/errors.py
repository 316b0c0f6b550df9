"""Exceptions raised by forcecal.

Every error a user can provoke with bad input (a mesh, a scene file, an HDF5
file, a parameter set, a time step) is one of these, with a message that names
the offending object (vertex, tet, connector, key, file). Nothing downstream
should ever see a NaN-filled result instead.
"""


class ForcecalError(Exception):
    """Base class of every error forcecal raises on purpose.

    Attributes:
        reached: how far the computation that failed got, in its own load parameter, when
            it knows: the indentation depth [m], the time [s] of a relaxation or an
            explicit run, the fraction of the load of a static solve [1]; None otherwise.
            Set by the raiser (or the caller that knows the parameter), read by the
            validation, which records it.
    """
    reached: float | None = None


class SceneError(ForcecalError):
    """A scene TOML file is missing, malformed, has unknown keys or bad values."""


class MeshError(ForcecalError):
    """A mesh is unusable: no tets, inverted/degenerate tets, duplicates, ..."""


class DataFileError(ForcecalError):
    """An HDF5 data file is missing, corrupt, of the wrong kind or mismatched."""


class ParameterError(ForcecalError):
    """Connector or material parameters are non-physical."""


class StabilityError(ForcecalError):
    """An explicit time step is above the stability limit, or a run diverged."""


class TimeStepError(StabilityError):
    """The explicit time step a scene sets (``particle.dt``) is above a model's stability limit:
    a setting to change (a refusal), not a failure of the model."""


class ConvergenceError(ForcecalError):
    """A nonlinear or optimisation solver failed to converge."""
