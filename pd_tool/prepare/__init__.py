"""Preparation: which Gaussians move, interior filling, the simulation grid, thin parts, and
the memory and run-time estimates that refuse a run before it starts."""
from pd_tool.prepare.preparation import Box, PreparedScene, PrepareOptions, prepare_scene, refine_for_thin

__all__ = ["Box", "PreparedScene", "PrepareOptions", "prepare_scene", "refine_for_thin"]
