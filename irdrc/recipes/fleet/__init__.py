"""``recipes/fleet.py`` (``recipe``): several vehicles' learners scored against the fleet's optimum,
and the ``report`` of a fleet's run (per vehicle and for the fleet)."""
