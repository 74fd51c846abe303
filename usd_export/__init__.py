"""USD export: the only package that imports pxr (usd-core >= 26.3), and lazily.

Public API (importing `usd_export` itself does not import pxr):

    UsdBakeWriter(path, *, n_points, fps, start_frame=0, up_axis="Z",
                  meters_per_unit=1.0, fmt="instancer" | "splat" | "both",
                  colors=None, opacities=None, sh=None, scale_factor=2.0,
                  ids=None, color_points=True, flush_bytes=64 MiB, threaded=False,
                  static=None)   # [N] bool: written once in the Static* prims
        .write_frame(time_code, positions [N,3] scene units,
                     orientations [N,4] (w,x,y,z) unit, scales [N,3] linear sigma)
        .hold_frames(until_time_code)   # object at rest: no samples, end time grows
        .close(validate=True) -> Path   # validate, then os.replace into place
        .abort()                        # delete temporaries, publish nothing
        context manager: close() on success, abort() on exception.
    validate_usd(path, *, usd_validators=True, every_sample=True) -> list[str]
        Every registered pxr.UsdValidation validator (errors fail, warnings are
        returned) plus pdtool's own checks (array lengths agree, unit quaternions,
        extent contains the points, stage metadata) at every time sample, or at the
        first and last with every_sample=False; raises UsdExportError.
    instance_positions(stage, time) -> (ids, positions)
        Every instance's position at `time`, sorted by id, across the moving
        (/Root/Instancer) and static (/Root/StaticInstancer) prims.
    instance_arrays(stage, time, names=("positions",)) -> (ids, static, {name: array})
        The same for positions, orientations (x, y, z, w as stored) and scales,
        with whether each instance sits in a static prim.
    UsdExportError   (pd_tool.core.errors; a PdToolError: the CLI exits 2)

Scales: the PointInstancer's unit-sphere prototype is scaled by
sigma * scale_factor (default 2: the ~2-sigma ellipsoid); the splat schema gets
the linear sigmas unchanged. Quaternions: pdtool passes (w, x, y, z); USD's
Vt arrays are filled from numpy as (x, y, z, w), Gf.Quat* take w first.

Example:
    from usd_export import UsdBakeWriter
    with UsdBakeWriter("out.usd", n_points=n, fps=30, fmt="both",
                       colors=rgb, opacities=alpha, sh=sh) as w:
        for f in range(frames):
            w.write_frame(f, positions[f], quats_wxyz[f], sigmas[f])

On disk: a single binary crate file OUT.usd (no sidecar files; while writing,
a hidden .OUT.usd.tmp-<pid>-<hex>.usdc sits next to it). Memory stays bounded
because the crate layer is saved incrementally every `flush_bytes` of samples
(saved arrays are then read back lazily from the mapped file), not through
value clips. Prims: /Root/Instancer (PointInstancer, unit-sphere prototype in
/Root/Instancer/Prototypes), /Root/SplatColors (Points with displayColor: the
only colour Blender imports), /Root/Splats (ParticleField3DGaussianSplat); the
instances passed as `static` go to /Root/StaticInstancer, /Root/StaticSplatColors
and /Root/StaticSplats instead, written once. A time-sampled attribute gets a
sample only when its value changes (a held pose, constant scales: one sample).
See docs/usd.md.
"""
from __future__ import annotations

from pd_tool.core.errors import UsdExportError

__all__ = ["UsdBakeWriter", "validate_usd", "instance_positions", "instance_arrays", "UsdExportError"]


def __getattr__(name: str):
    # Lazy: pxr is a heavy import and only bake/export needs it.
    if name in ("UsdBakeWriter", "validate_usd", "instance_positions", "instance_arrays"):
        try:
            if name == "UsdBakeWriter":
                from .writer import UsdBakeWriter as obj
            elif name == "validate_usd":
                from .validate import validate_usd as obj
            elif name == "instance_arrays":
                from .validate import instance_arrays as obj
            else:
                from .validate import instance_positions as obj
        except ImportError as e:
            if "pxr" in str(e):
                raise UsdExportError("USD export needs usd-core: pip install 'usd-core>=26.3'") from e
            raise
        return obj
    raise AttributeError(f"module 'usd_export' has no attribute {name!r}")
