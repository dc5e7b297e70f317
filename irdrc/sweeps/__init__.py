"""The sweep engine: a grid of overrides, each point one run of a recipe, on Ray Tune or one after
another here.

- ``trials``: ``plan`` (every point composed and checked on the driver, for the recipe module the
  caller hands it) and ``execute`` (the executors, ``summary.csv``, resume);
- ``point``: one point run into its directory, its status and files; ``tune_runner``: the Ray Tune
  executor; ``seeds``: mean ± 95 % intervals and banded curves over seeds.

A point carries its recipe module's path, which a worker imports: the engine imports no recipe.

May import: ``irdrc.core``, ``irdrc.runs``, Ray (lazily). No recipe, nothing of ``irdrc.paper``.
"""
