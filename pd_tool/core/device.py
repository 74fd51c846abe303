"""Choosing the compute device: CUDA when present, CPU otherwise; --device overrides."""
from __future__ import annotations

import contextlib
import os
import re
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


# How torch and warp word a failed allocation: torch.OutOfMemoryError (CUDA), torch's CPU
# "DefaultCPUAllocator: can't allocate memory", warp's "Failed to allocate N bytes on device
# 'cuda:0'" and its CUDA error 2 ("out of memory").
_ALLOCATION_FAILED = re.compile(r"Failed to allocate \d+ bytes on device '(?P<device>[^']+)'|out of memory"
                                r"|can't allocate memory", re.IGNORECASE)


def out_of_memory_line(error: BaseException) -> str | None:
    """One line for a failed allocation (MemoryError, or a device's), naming how full the
    GPU is and the ways out; None for any other error. Running out of memory is no bug in
    the scene or in pdtool: a larger scene or another process on the same GPU causes it."""
    import torch

    host = "out of memory; lower --quality, the driver ratio or the grid resolution"
    if isinstance(error, MemoryError):
        return host
    m = _ALLOCATION_FAILED.search(str(error)) if isinstance(error, RuntimeError) else None
    if m is None and not isinstance(error, torch.OutOfMemoryError):
        return None
    named = m.group("device") if m else None
    gpu = named.startswith("cuda") if named else (isinstance(error, torch.OutOfMemoryError) or "CUDA" in str(error))
    if not gpu:
        return host
    where = ""
    with contextlib.suppress(Exception):
        free, total = torch.cuda.mem_get_info()
        where = f" ({free / 2**30:.1f} of {total / 2**30:.1f} GiB free now)"
    return (f"out of GPU memory{where}; close other programs or jobs using this GPU (pdtool batch runs "
            "one job per GPU), lower --quality, the driver ratio or the grid resolution, or use --device cpu")


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
