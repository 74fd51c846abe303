"""Peak-memory estimates for a bake and a fit, and the check that refuses a run that
cannot fit before any heavy work starts.

An estimate is the memory a run adds on top of a process that has already imported
pdtool and loaded the scene (what the command has when it calls the check), in bytes,
split into host (RAM) and device (GPU) memory. It is a sum of terms, each the size of
buffers the code allocates (read from pd_tool/sim/solver.py, autograd.py, the rasteriser,
the drivers' k-means/k-NN and the writers) times a per-element byte count. Byte counts
marked "measured" were fitted to the peak RSS of fresh processes
(bench/memory_estimate.py, docs/reliability.md); the others are array sizes.

On CUDA the particle, grid, render and autograd buffers live on the GPU; the host then
holds the runtime, the scene copies the writers need and the preview frames.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

from pd_tool.core.device import host_available_bytes
from pd_tool.core.errors import PdToolError

GiB = float(1 << 30)
MiB = float(1 << 20)

# --- the process: first use of warp kernels, USD plugins, torch's CPU pools, ffmpeg (measured)
RUNTIME_HOST_BAKE = 280 * MiB  # measured 225 MiB with warp's kernels cached, about 340 in a fresh clone that compiles them: the midpoint
RUNTIME_HOST_FIT = 236 * MiB
RUNTIME_DEVICE = 64 * MiB  # warp's and torch's CUDA pools beyond the context (context excluded:
#                            it exists before mem_get_info is read)

# --- per element, bytes
B_GAUSS_BAKE = 1150  # measured: preparation (float64 copies), animator tables, per-frame arrays, USD
# on the GPU: the scene, the animator's neighbours and rest poses, a frame's interpolation;
# measured: the device memory bakes of the thin plant took at 1M-10M Gaussians (H200)
# less the other terms, 6.5 GB at 10M
B_GAUSS_BAKE_DEVICE = 350
B_DRIVER = 400  # particle state u, v, C, F + base, E, volume, mass, static, order, sorted copies
B_NODE = 32  # grid m (4) + mv (12) + v (12) + fixed (4)
B_PAIR = 5  # measured: k-NN / k-means (query, candidate) pairs resident per chunk element
KNN_CHUNK = 1 << 22  # pd_tool.drivers.knn.DEFAULT_CHUNK: pairs held at once on the CPU
KNN_CHUNK_CUDA = 1 << 24  # pd_tool.drivers.knn.CUDA_CHUNK: ... on a GPU
B_PAIR_CUDA = 75  # measured: torch's peak per pair of the torch search, 1M / 3M points, H200
KNN_GRID_CELLS = 1 << 22  # pd_tool.drivers.knn._GRID_MAX_CELLS: the hash grid's buckets at most
KNN_SAMPLE = 256  # pd_tool.drivers.knn._SAMPLE: queries searched by brute force to size the grid
PREVIEW_PIXELS = 480 * 270  # the bake's automatic preview camera
# fit
B_GAUSS_FIT = 1500  # measured: scene on the device, animator, fields' inputs
B_GAUSS_FRAME = 700  # measured: autograd graph per rendered frame and Gaussian (animator + projection)
B_DRIVER_FRAME = 4 * (3 + 3 + 9 + 9) * 3  # saved (x, v, C, F) in, out and cotangents per simulated frame
B_PIXEL_FRAME = 4 * 3 * 12  # loss graph per pixel: image, L1, SSIM's blurred maps
B_PIXEL_VIDEO = 4 * 4  # reference frame (RGB float32) + mask per pixel


@dataclass
class MemoryEstimate:
    """Bytes a run will add at its peak, and where each term comes from."""

    host: float
    device: float  # 0 on CPU
    terms: dict[str, float] = field(default_factory=dict)  # name -> bytes (host or device)

    def describe(self) -> str:
        s = f"{self.host / GiB:.2f} GiB host"
        return s + (f" + {self.device / GiB:.2f} GiB GPU" if self.device else "")


class InsufficientMemory(PdToolError):
    """The run's estimated peak memory exceeds what is available."""


def _knn_workspace(n_points: int, n_drivers: int, gpu: bool) -> float:
    # K-Means assigns every point to its nearest centre and the animator finds 8 drivers per
    # Gaussian. The hash-grid pass holds each query's 8 distances and indices, the grid's
    # buckets and its sorted references; sizing the grid searches a sample by brute force,
    # a quarter chunk of pairs at a time. The torch search sees only the few queries the
    # grid leaves, far fewer pairs than a chunk. Buckets: a cell is about a neighbour
    # distance wide, so a surface of Q references spans about Q^1.5 of them.
    chunk, per_pair = (KNN_CHUNK_CUDA, B_PAIR_CUDA) if gpu else (KNN_CHUNK, B_PAIR)
    q = max(n_drivers, 1)
    grid = 12 * 8 * max(n_points, 1) + 8 * min(KNN_GRID_CELLS, q ** 1.5) + 16 * q
    return grid + per_pair * min(chunk // 4, KNN_SAMPLE * q)


def estimate_bake_memory(
    *,
    n_gaussians: int,
    n_simulated: int,
    driver_ratio: float,
    grid_dims: tuple[int, int, int],
    frames: int,
    preview_pixels: int = 0,
    sh_coeffs: int = 1,
    device: str = "cpu",
) -> MemoryEstimate:
    """Peak memory of `pd_tool.bake.baker.bake`.

    Args:
        n_gaussians: Gaussians in the scene (all are animated and written).
        n_simulated: simulated points: foreground Gaussians plus interior fill particles
            (the drivers are chosen among them).
        driver_ratio: drivers per simulated Gaussian.
        grid_dims: simulation grid cells (nx, ny, nz); nodes are cells + 1 per axis.
        frames: frames in the animation.
        preview_pixels: width * height of the preview / frames-out renders (0: none).
        sh_coeffs: SH coefficients per colour channel (1, 4, 9, 16): the USD splat field.
        device: "cpu" or "cuda[:i]".
    """
    q = max(1, int(math.ceil(driver_ratio * n_simulated)))
    nodes = math.prod(d + 1 for d in grid_dims)
    gpu = str(device).startswith("cuda")
    terms = {
        "runtime": RUNTIME_HOST_BAKE,
        "gaussians": float(B_GAUSS_BAKE + 12 * sh_coeffs) * n_gaussians,
        "drivers": float(B_DRIVER) * q,
        "grid": float(B_NODE) * nodes,
        "knn": _knn_workspace(n_simulated, q, gpu),
        # every preview frame is kept as uint8 RGB until the video is encoded
        "preview": 3.0 * preview_pixels * frames + (40.0 * preview_pixels if preview_pixels else 0.0),
    }
    on_device = ("drivers", "grid", "knn") if gpu else ()
    host = sum(v for k, v in terms.items() if k not in on_device)
    dev = sum(terms[k] for k in on_device) + (RUNTIME_DEVICE + B_GAUSS_BAKE_DEVICE * n_gaussians if gpu else 0.0)
    return MemoryEstimate(host=host, device=dev, terms=terms)


def estimate_fit_memory(
    *,
    n_gaussians: int,
    n_simulated: int,
    driver_ratio: float,
    grid_dims: tuple[int, int, int],
    frames: list[int],
    image_pixels: int,
    stage1_frames: int = 3,
    segment: int = 16,
    device: str = "cpu",
) -> MemoryEstimate:
    """Peak memory of `pd_tool.fit.run.run_fit`.

    The peak is the stage-2 backward: every frame of every video is simulated and rendered
    before the one backward pass, so the graph holds each frame's saved simulation state,
    animated Gaussians and loss maps; the simulation itself is checkpointed (it replays
    `segment` substeps under a tape: segment + 1 particle states and `segment` grids with
    gradients). Frames the simulation stores for the backward come on top, within the
    budget stored_frames_budget_mb gives from what this estimate leaves free.

    Args:
        n_gaussians, n_simulated, driver_ratio, grid_dims: as for estimate_bake_memory.
        frames: frames per reference video.
        image_pixels: width * height of the (resized) reference frames.
        stage1_frames: frames stage 1 back-propagates through.
        segment: SimConfig.segment, substeps per tape.
        device: "cpu" or "cuda[:i]".
    """
    q = max(1, int(math.ceil(driver_ratio * n_simulated)))
    nodes = math.prod(d + 1 for d in grid_dims)
    total_frames = sum(max(t - 1, 0) for t in frames)
    s1 = sum(min(stage1_frames, max(t - 1, 0)) for t in frames)
    graph_frames = max(total_frames, s1)
    gpu = str(device).startswith("cuda")
    terms = {
        "runtime": RUNTIME_HOST_FIT,
        "gaussians": float(B_GAUSS_FIT) * n_gaussians,
        "drivers": float(B_DRIVER) * q,
        "videos": float(B_PIXEL_VIDEO) * image_pixels * sum(frames),
        "graph": graph_frames * (float(B_GAUSS_FRAME) * n_gaussians + float(B_DRIVER_FRAME) * q
                                 + float(B_PIXEL_FRAME) * image_pixels),
        # the tape pool (with gradients: x2) plus the untaped grid
        "tape": (segment + 1) * 2.0 * 96 * q + (2 * segment + 1) * float(B_NODE) * nodes,
        "knn": _knn_workspace(n_simulated, q, gpu),
    }
    on_device = ("gaussians", "drivers", "videos", "graph", "tape", "knn") if gpu else ()
    host = sum(v for k, v in terms.items() if k not in on_device)
    dev = sum(terms[k] for k in on_device) + (RUNTIME_DEVICE if gpu else 0.0)
    if gpu:  # the host still keeps the scene and the frames it loaded
        host += 200.0 * n_gaussians + 12.0 * image_pixels * sum(frames)
    return MemoryEstimate(host=host, device=dev, terms=terms)


STORED_FRAMES_CPU_MB = 1024.0  # the most RAM a CPU fit fills with frames stored for the backward


def stored_frames_budget_mb(estimate: MemoryEstimate, available: tuple[float, float | None]) -> float:
    """MB the fit's simulator may fill with frames its forward stores for the backward
    (SimConfig.keep_budget_mb): half of what the estimate leaves free, of GPU memory on
    CUDA, of RAM on the CPU (there at most STORED_FRAMES_CPU_MB). Frames beyond it are
    recomputed, so this trades memory for time only; 0 when the estimate leaves nothing."""
    host, gpu = available
    if gpu is not None:
        return max(0.0, 0.5 * (gpu - estimate.device) / MiB)
    return max(0.0, min(STORED_FRAMES_CPU_MB, 0.5 * (host - estimate.host) / MiB))


def available_memory(device: str = "cpu") -> tuple[float, float | None]:
    """(host bytes available, GPU bytes free or None on CPU). Host: MemAvailable from
    /proc/meminfo (inf where there is none, e.g. macOS: then no host check)."""
    gpu = None
    if str(device).startswith("cuda"):
        import torch

        free, _total = torch.cuda.mem_get_info(torch.device(device))
        gpu = float(free)
    return host_available_bytes(), gpu


def check_memory(estimate: MemoryEstimate, *, what: str, quality: str, driver_ratio: float, resolution: str,
                 device: str = "cpu", available: tuple[float, float | None] | None = None) -> None:
    """Raise InsufficientMemory (one line) when `estimate` exceeds the available memory.

    what: "bake" or "fit"; quality, driver_ratio, resolution: the current values of the
    options that reduce memory, named in the message. available: (host, gpu) bytes; None
    reads them (available_memory). PDTOOL_SKIP_MEMORY_CHECK=1 disables the check.
    """
    if os.environ.get("PDTOOL_SKIP_MEMORY_CHECK") == "1":
        return
    host_free, gpu_free = available if available is not None else available_memory(device)
    short = []
    if estimate.host > host_free:
        short.append(f"{estimate.host / GiB:.2f} GiB of RAM but {host_free / GiB:.2f} GiB is available")
    if gpu_free is not None and estimate.device > gpu_free:
        short.append(f"{estimate.device / GiB:.2f} GiB of GPU memory but {gpu_free / GiB:.2f} GiB is free")
    if short:
        raise InsufficientMemory(
            f"this {what} needs about {' and '.join(short)}; lower --quality (now {quality}), "
            f"the driver ratio (now {driver_ratio:g}, set by the quality preset) or the resolution ({resolution})"
        )
