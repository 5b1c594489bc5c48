"""End-to-end runs that chain the stages (synthesise or load, reconstruct, materials, identify, simulate, report)."""

from endogsim.pipeline.preview import PreviewConfig, build_preview_scene, render_preview

__all__ = ["PreviewConfig", "build_preview_scene", "render_preview"]
