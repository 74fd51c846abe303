"""Choosing the compute device: CUDA when present, CPU otherwise; --device overrides."""
from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator

from pd_tool.core.errors import PdToolError

DEVICES = ("auto", "cpu", "cuda")


@contextlib.contextmanager
def native_stderr_silenced() -> Iterator[None]:
    """File descriptor 2 on /dev/null for the block: what native code and child processes
    started in it write there (Python's own sys.stderr included) goes nowhere."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def init_warp_quietly() -> None:
    """Initialise warp without its banner, and without the native library's
    "could not load the CUDA driver" line on machines with no GPU: a user's stderr should
    hold pdtool's own messages only."""
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    if getattr(init_warp_quietly, "_done", False):
        return
    with native_stderr_silenced():
        wp.init()
    init_warp_quietly._done = True  # type: ignore[attr-defined]


def host_available_bytes() -> float:
    """RAM available to a new allocation: MemAvailable from /proc/meminfo, in bytes; inf where
    there is none (e.g. macOS)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    return float("inf")


def cuda_available() -> bool:
    """True when both torch and warp see a CUDA device."""
    import torch

    init_warp_quietly()
    if not torch.cuda.is_available():
        return False
    import warp as wp

    return wp.is_cuda_available()


def resolve_device(name: str | None = "auto") -> str:
    """'cpu' or 'cuda' for a user's choice ('auto', 'cpu', 'cuda' or None = auto)."""
    name = (name or "auto").lower()
    init_warp_quietly()  # also for --device cpu: no banner before pdtool's own output
    if name not in DEVICES:
        raise PdToolError(f"--device {name!r} is not one of {', '.join(DEVICES)}")
    if name == "auto":
        return "cuda" if cuda_available() else "cpu"
    if name == "cuda" and not cuda_available():
        raise PdToolError("--device cuda: no CUDA GPU visible to torch and warp; use --device cpu or install a CUDA build of torch")
    return name
