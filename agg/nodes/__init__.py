"""Scene-graph nodes (paper Sec. 3): the camera, and Gaussian parameter sets with optimiser-state surgery.

The background, rigid, non-rigid and sky nodes and ``compose(t)`` are still to come (issue 4).
"""
