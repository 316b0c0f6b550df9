"""Real-time particle model: one particle per vertex, one Maxwell-Solid connector per edge.

Public API (Warp ``warp.sim`` style: immutable Model of flat arrays built by a
builder, mutable State, integrators and solvers apart):

- :mod:`particle.model`: :class:`ConnectorParams`, :class:`Model`,
  :class:`ModelBuilder`, :func:`build_model`, :class:`State`.
- :mod:`particle.integrator`: :class:`VerletIntegrator`, :func:`critical_time_step`,
  :func:`strain_range_for_release`, :func:`resolve_time_step`, :class:`Prescribed`.
- :mod:`particle.statics`: Newton equilibrium, :func:`gravity_static` (the tangent
  factorised by :mod:`particle.sparse_ldl`).
- :mod:`particle.evaluators`: :class:`IndentationEvaluator`,
  :class:`RelaxationEvaluator` (batch force curves for calibration).
- :mod:`particle.experiments`: :func:`gravity_dynamic`, :func:`relaxation_dynamic`.
- :mod:`particle.haptics`: :class:`HapticSession`.
- :mod:`particle.volume`: the optional per-tet volume term (``ConnectorParams.kv``,
  elastic or with Maxwell arms ``kv1, bv1, kv2, bv2``): forces, tangent, energy, its part
  of the stability bound.
- :mod:`particle.nodal_volume`: the same term on one volume constraint per particle (its
  one-ring's volume, ``Model.volume_element = "nodal"``), which does not lock bending.
"""
import forcecal  # noqa: F401  (settles the numba cache folder before numba is imported: forcecal.caches)
import particle.numba_fixes  # noqa: F401  (fixes numba's inliner before anything is compiled)
import particle.numba_cache  # noqa: F401  (cached kernels keyed on the kernel sources: before any is decorated)
from particle.evaluators import IndentationEvaluator, RelaxationEvaluator
from particle.experiments import gravity_dynamic, relaxation_dynamic
from particle.haptics import HapticSession
from particle.integrator import VerletIntegrator
from particle.stability import critical_time_step, resolve_time_step, strain_range_for_release
from particle.model import Model, ModelBuilder, Prescribed, State, build_model
from particle.params import ConnectorParams
from particle.statics import gravity_static

__all__ = ["ConnectorParams", "HapticSession", "IndentationEvaluator", "Model", "ModelBuilder",
           "Prescribed", "RelaxationEvaluator", "State", "VerletIntegrator", "build_model",
           "critical_time_step", "gravity_dynamic", "gravity_static", "relaxation_dynamic",
           "resolve_time_step", "strain_range_for_release"]
