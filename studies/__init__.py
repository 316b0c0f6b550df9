"""Studies: investigations that answered one question of the project once, one module each.

Each study has one entry point (``python -m studies.<name> ...``), writes its results under
``runs/studies/`` and says in its docstring what it measures. Unlike the benchmarks
(:mod:`pipelines.bench`, ``make bench``) they are not rerun routinely. They may import
forcecal; nothing of forcecal imports them. ``docs/studies.md`` lists them with their
questions, commands and results (``python -m studies.catalogue``).
"""
