"""Input and output: video / image ingest (``video``), the scene bundle format (``bundle``), importers."""

from agg.io.bundle import SceneBundle, SemanticFeatures, Tracklets, compute_scale_factor, rebase_to_first_camera
from agg.io.video import IngestConfig, IngestResult, ingest, ingest_to_bundle

__all__ = ["SceneBundle", "SemanticFeatures", "Tracklets", "compute_scale_factor", "rebase_to_first_camera",
           "IngestConfig", "IngestResult", "ingest", "ingest_to_bundle"]
