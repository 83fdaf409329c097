"""AGG: Adaptive Gaussian Graph reconstruction of driving videos.

The engine is a library: it imports nothing from ``service`` or ``worker``.
"""

__version__ = "0.1.0"
