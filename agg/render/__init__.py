"""The differentiable Gaussian renderer: ``rasterize`` (see agg/render/rasterize.py)."""

from agg.render.rasterize import BACKENDS, RenderMeta, RenderOutput, rasterize

__all__ = ["BACKENDS", "RenderMeta", "RenderOutput", "rasterize"]
