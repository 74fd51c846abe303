"""Bake: simulate a prepared object under a force and stream the animation to USD and
splat files."""
from pd_tool.bake.baker import BakeResult, BakeSettings, ForceSpec, bake

__all__ = ["BakeResult", "BakeSettings", "ForceSpec", "bake"]
