"""Run infrastructure shared by every recipe: config schema and checks, the harness (seeding,
evaluation, metrics, summary), checkpoints and resume, and the ``make_*`` factories."""
