"""Importers of existing dataset layouts into scene bundles (see docs/BUNDLE.md).

Each ``import_X(source, out, ...)`` writes a bundle at ``out`` and returns it as a ``SceneBundle``; poses come out in
OpenCV camera axes with the first camera as the world origin.
"""

from agg.io.importers.colmap import import_colmap
from agg.io.importers.kitti import import_kitti
from agg.io.importers.nerfstudio import import_nerfstudio

__all__ = ["import_colmap", "import_kitti", "import_nerfstudio"]
