"""Scene-graph nodes (paper Sec. 3): the camera node (``camera.py``), Gaussian parameter sets with optimiser-state
surgery (``gaussians.py``), rigid agents with per-frame poses and validity (``rigid.py``), and their initialisation
from a scene bundle (``init.py``). ``agg/graph.py`` composes them.

The non-rigid and sky nodes are still to come (issue 4).
"""
