"""Run infrastructure shared by every recipe: the lifecycle (``lifecycle.recipe_main``), the
harness (metrics, evaluation, summary), checkpoints and resume, config schema and checks, the memory
estimate, and the implementation switch (``implementation``: fast | reference)."""
import logging

# The run's record (lifecycle, checkpoint): silent until Hydra's job logging gives it its file
# (conf/hydra/job_logging/run_log.yaml), as the logging HOWTO asks of a library.
logging.getLogger(__name__).addHandler(logging.NullHandler())
