"""``make bench``: every benchmark of forcecal, one module per item or study.

- :mod:`pipelines.bench.driver`: the ``bench`` command (the order of its items, the studies
  of :data:`~pipelines.bench.driver.STUDIES`, ``--only``, ``bench.json``);
- :mod:`pipelines.bench.items`: the items that measure the default scene (default run,
  time-step sweep, FE discretisation study, reference timings, particle engine);
- :mod:`pipelines.bench.configs`: the run time vs error configurations (cached pipelines);
- :mod:`pipelines.bench.particle_engine`: kernel throughput, real-time gravity, term skipping,
  haptic latency, evaluator times;
- :mod:`pipelines.bench.stability`: estimated vs empirical stability limits;
- the studies: :mod:`~pipelines.bench.experiments`, :mod:`~pipelines.bench.haptic`,
  :mod:`~pipelines.bench.fe_convergence`, :mod:`~pipelines.bench.scale`,
  :mod:`~pipelines.bench.calibration_methods`, :mod:`~pipelines.bench.volume`;
- :mod:`pipelines.bench.report`: ``BENCH.md`` and ``pareto.png`` from ``bench.json``;
- :mod:`pipelines.bench.release_levers`: not an item (run on its own, on a finished run):
  what a consistent mass and a relaxing volume term would do to the gravity release;
- :mod:`pipelines.bench.sag_split`: not an item either: how the static sag depends on the
  calibrated model's split between springs and ``kv``, and where;
- :mod:`pipelines.bench.sag_tradeoff`: not an item: whether region-wise scalings of the
  calibrated model could fit its punch curves and hang like the FE at once (a diagnostic
  with the FE sag as a constraint, never a calibration);
- :mod:`pipelines.bench.fold_cv`: not an item: k-fold cross-validation of whole calibrations
  over the calibration points, to choose between calibration settings;
- :mod:`pipelines.bench.finished_run`: what those four studies share: the finished run
  folder they read and their two command-line arguments.

Importing this package imports none of them (each item loads its own module when it runs).
"""
