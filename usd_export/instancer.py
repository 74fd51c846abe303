"""UsdGeom.PointInstancer of unit spheres, plus a companion UsdGeom.Points for colour.

Layout under the root prim (default paths):

    /Root/Instancer                 PointInstancer
        positions       point3f[]   time-sampled, scene units
        orientations    quath[]     time-sampled (quath: Blender 5.0 ignores orientationsf)
        scales          float3[]    time-sampled, = Gaussian sigma * scale_factor
        extent          float3[2]   time-sampled, tight box of the scaled spheres
        protoIndices    int[]       once (all 0)
        ids             int64[]     once
        primvars:displayColor   color3f[] once, linear (sRGB EOTF of the 3DGS colour), interpolation vertex (per instance)
        primvars:displayOpacity float[]   once, interpolation vertex
    /Root/Instancer/Prototypes/Sphere   Sphere, radius 1 (the unit sphere)
    /Root/SplatColors               Points
        points          point3f[]   time-sampled, same values as Instancer.positions
        widths          float[]     once, = 2 * mean sigma * scale_factor at the first frame
        extent          float3[2]   time-sampled
        primvars:displayColor / displayOpacity, interpolation vertex

Blender's USD importer drops PointInstancer primvars, so the per-splat colour
reaches Blender only through SplatColors (imported as a point cloud with a
`displayColor` attribute). Other DCCs see both prims; pass
`color_points=False` to the writer to leave SplatColors out.
"""
from __future__ import annotations

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from ._geom import ellipsoid_extent, sphere_extent
from ._held import Held


class InstancerPart:
    """Defines the instancer prims on a stage and turns frames into time samples."""

    def __init__(self, stage: Usd.Stage, path: str, *, colors: np.ndarray,
                 opacities: np.ndarray, ids: np.ndarray, scale_factor: float,
                 color_points_path: str | None) -> None:
        n = colors.shape[0]
        self.scale_factor = float(scale_factor)
        inst = UsdGeom.PointInstancer.Define(stage, path)
        protos = UsdGeom.Scope.Define(stage, f"{path}/Prototypes")
        sphere = UsdGeom.Sphere.Define(stage, f"{protos.GetPath()}/Sphere")
        sphere.CreateRadiusAttr(1.0)
        sphere.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-1.0), Gf.Vec3f(1.0)]))
        inst.CreatePrototypesRel().SetTargets([sphere.GetPath()])
        inst.CreateProtoIndicesAttr(Vt.IntArray.FromNumpy(np.zeros(n, dtype=np.int32)))
        inst.CreateIdsAttr(Vt.Int64Array.FromNumpy(ids.astype(np.int64)))
        pv = UsdGeom.PrimvarsAPI(inst)
        pv.CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray,
                         UsdGeom.Tokens.vertex).Set(Vt.Vec3fArray.FromNumpy(colors))
        pv.CreatePrimvar("displayOpacity", Sdf.ValueTypeNames.FloatArray,
                         UsdGeom.Tokens.vertex).Set(Vt.FloatArray.FromNumpy(opacities))
        # Time-sampled attributes get their specs (type) now and values per frame.
        self.positions = inst.CreatePositionsAttr().GetPath()
        self.orientations = inst.CreateOrientationsAttr().GetPath()
        self.scales = inst.CreateScalesAttr().GetPath()
        self.extent = inst.CreateExtentAttr().GetPath()
        # sigmas -> (instance radii, their Vt array)
        self._radii = Held(lambda s: (r := s * np.float32(self.scale_factor), Vt.Vec3fArray.FromNumpy(r)))

        self.points = None
        if color_points_path is not None:
            pts = UsdGeom.Points.Define(stage, color_points_path)
            pts.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(Vt.Vec3fArray.FromNumpy(colors))
            pts.CreateDisplayOpacityPrimvar(UsdGeom.Tokens.vertex).Set(Vt.FloatArray.FromNumpy(opacities))
            self.points = pts.CreatePointsAttr().GetPath()
            self.points_extent = pts.CreateExtentAttr().GetPath()
            self.widths = pts.CreateWidthsAttr().GetPath()
            pts.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
            self._point_radii: np.ndarray | None = None

    def first_frame_defaults(self, positions: np.ndarray, quats: np.ndarray,
                             sigmas: np.ndarray, xyzw16: np.ndarray) -> list[tuple[Sdf.Path, object]]:
        """Non-animated values that need a frame to compute (point widths)."""
        if self.points is None:
            return []
        self._point_radii = (sigmas.mean(axis=1) * self.scale_factor).astype(np.float32)
        return [(self.widths, Vt.FloatArray.FromNumpy(2.0 * self._point_radii))]

    def samples(self, positions: np.ndarray, quats: np.ndarray,
                sigmas: np.ndarray, xyzw16: np.ndarray) -> list[tuple[Sdf.Path, object]]:
        """Time samples for one frame: positions [N,3] f32, quats [N,4] wxyz (any length),
        sigmas [N,3], xyzw16 [N,4] the unit quaternions as written (_geom.unit_xyzw_half)."""
        radii, radii_vt = self._radii(sigmas)
        pos_vt = Vt.Vec3fArray.FromNumpy(positions)
        # The extent bounds the unit spheres as instanced, from the float quaternions;
        # the quath rounding (~5e-4) moves a sphere's surface far less than the
        # outward float32 rounding margin of the box relative to typical radii.
        out = [
            (self.positions, pos_vt),
            (self.orientations, Vt.QuathArray.FromNumpy(xyzw16)),
            (self.scales, radii_vt),
            (self.extent, Vt.Vec3fArray.FromNumpy(ellipsoid_extent(positions, quats, radii))),
        ]
        if self.points is not None:
            out.append((self.points, pos_vt))
            out.append((self.points_extent,
                        Vt.Vec3fArray.FromNumpy(sphere_extent(positions, self._point_radii))))
        return out
