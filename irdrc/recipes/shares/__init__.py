"""The radar share's learners: ``recipes/sac.py`` (``sac``) and ``recipes/ppo.py`` (``ppo``), on
their shared ``learning`` (the run every learner of the share finishes the same way)."""
