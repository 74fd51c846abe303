"""Differentiable tile-based 3D Gaussian Splatting rasteriser (warp kernels, CPU and CUDA).

Public API: ``render`` and ``RenderOutput`` (see api.py). The warp import happens on the
first call to ``render``.
"""
from pd_tool.render.api import RenderInputError, RenderOutput, render

__all__ = ["RenderInputError", "RenderOutput", "render"]
