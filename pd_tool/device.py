"""Choosing the compute device: CUDA when present, CPU otherwise; --device overrides."""
from __future__ import annotations

from pd_tool.errors import PdToolError

DEVICES = ("auto", "cpu", "cuda")


def cuda_available() -> bool:
    """True when both torch and warp see a CUDA device."""
    import torch

    if not torch.cuda.is_available():
        return False
    import warp as wp

    wp.config.quiet = True
    wp.init()
    return wp.is_cuda_available()


def resolve_device(name: str | None = "auto") -> str:
    """'cpu' or 'cuda' for a user's choice ('auto', 'cpu', 'cuda' or None = auto)."""
    name = (name or "auto").lower()
    if name not in DEVICES:
        raise PdToolError(f"--device {name!r} is not one of {', '.join(DEVICES)}")
    if name == "auto":
        return "cuda" if cuda_available() else "cpu"
    if name == "cuda" and not cuda_available():
        raise PdToolError("--device cuda: no CUDA GPU visible to torch and warp; use --device cpu or install a CUDA build of torch")
    return name
