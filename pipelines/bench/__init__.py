"""``make bench`` and ``make bench-full``: forcecal's speed and error on this machine.

- :mod:`pipelines.bench.driver`: the ``bench`` command (its items and their order, which of
  them ``make bench`` runs and at what size, ``--only``, ``bench.json``);
- :mod:`pipelines.bench.items`: the items that measure the default scene (default run,
  time-step sweep, FE discretisation study, reference timings, particle engine);
- :mod:`pipelines.bench.configs`: the run time vs error configurations (cached pipelines);
- :mod:`pipelines.bench.particle_engine`: kernel throughput, real-time gravity, term skipping,
  haptic latency, evaluator times;
- :mod:`pipelines.bench.stability`: estimated vs empirical stability limits, on the cases
  of :mod:`~pipelines.bench.stability_cases` with the bisection of
  :mod:`~pipelines.bench.empirical_limit` (the tests check the same);
- the other items: :mod:`~pipelines.bench.experiments`, :mod:`~pipelines.bench.haptic`,
  :mod:`~pipelines.bench.fe_convergence`, :mod:`~pipelines.bench.scale`,
  :mod:`~pipelines.bench.calibration_methods`, :mod:`~pipelines.bench.volume`;
- :mod:`pipelines.bench.report`: ``BENCH.md`` and ``pareto.png`` from ``bench.json``.

Investigations that answered one question once live in the top-level ``studies`` package
(``docs/studies.md``); they may import the bench, never the reverse.

Importing this package imports none of them (each item loads its own module when it runs).
"""
