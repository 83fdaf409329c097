"""Scene-graph nodes (paper Sec. 3): the camera node (``camera.py``), Gaussian parameter sets with optimiser-state
surgery (``gaussians.py``), rigid agents with per-frame poses and validity (``rigid.py``), non-rigid agents
deformed by an MLP over canonical position, time and an instance embedding (``nonrigid.py``), the sky / far-field
node and the rule deciding whether a clip has sky (``sky.py``), and their initialisation from a scene bundle
(``init.py``). ``agg/graph.py`` composes them.
"""
