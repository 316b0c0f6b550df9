"""Studies: measurements that inform a choice of the project, one module per study.

Each study has one entry point (``python -m studies.<name> ...``), writes its results under
``runs/studies/`` and says in its docstring what it measures and how to rerun it. Unlike the
bench (:mod:`pipelines.bench`) they are not rerun by ``make bench``: each answers one
question once, on the run folders it names.

* :mod:`studies.viscoelastic_volume`: the relaxing (viscoelastic) volume term against the
  elastic one, calibrated on the committed scenes with the volume term.
* :mod:`studies.haptic_cost`: the haptic step's time per call with springs only, the elastic
  and the viscoelastic volume term.
"""
