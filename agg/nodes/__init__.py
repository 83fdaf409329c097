"""Scene-graph nodes (paper Sec. 3): the camera node (``camera.py``), Gaussian parameter sets with optimiser-state
surgery (``gaussians.py``) and rigid agents with per-frame poses and validity (``rigid.py``).

The background, non-rigid and sky nodes and the graph's ``compose(t)`` are still to come (issue 4).
"""
