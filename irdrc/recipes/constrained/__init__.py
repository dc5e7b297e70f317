"""``recipes/constrained.py`` (``recipe``): the most data subject to a miss-detection target, its
``frontier`` against the r4 route, and the trade-off ``region`` over the radar share."""
