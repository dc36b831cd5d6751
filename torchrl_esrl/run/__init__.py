"""Run infrastructure shared by every recipe: the lifecycle (``lifecycle.recipe_main``), the
harness (metrics, evaluation, summary), checkpoints and resume, config schema and checks, and
the ``make_*`` factories."""
