"""UsdVol.ParticleField3DGaussianSplat: the native 3D Gaussian splat schema (USD >= 26.03).

    /Root/Splats                    ParticleField3DGaussianSplat
        positions       point3f[]   time-sampled, scene units
        orientationsh   quath[]     time-sampled, unit (the schema's half-precision
                                    orientations: the same array as the instancer's
                                    quath, which the crate stores once for both)
        scales          float3[]    time-sampled, linear sigma (not log, not scaled)
        extent          float3[2]   time-sampled: box of the 3-sigma ellipsoids
                                    (the schema's kernel holds 99.7% there)
        opacities       float[]     once, 0-1 (activated, not logits)
        radiance:sphericalHarmonicsDegree       uniform int, d
        radiance:sphericalHarmonicsCoefficients float3[] once, N * (d+1)^2 values:
                        per splat its (d+1)^2 RGB coefficients contiguously, in the
                        3DGS order (DC first, then band 1, 2, 3 with m = -l..l), raw
                        coefficients (colour = 0.5 + 0.2821 * dc for degree 0).
        primvars:displayColor   color3f[] once, linear (sRGB EOTF of the 3DGS colour), for viewers without SH

The SH are constant over time: pdtool rotates Gaussians but does not rotate
their view-dependent colour (the PhysDreamer renderer does the same).
"""
from __future__ import annotations

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdVol, Vt

from ._geom import SPLAT_SUPPORT_SIGMAS, ellipsoid_extent, sh_degree
from ._held import Held


class SplatFieldPart:
    """Defines the splat prim on a stage and turns frames into time samples."""

    def __init__(self, stage: Usd.Stage, path: str, *, colors: np.ndarray,
                 opacities: np.ndarray, sh: np.ndarray) -> None:
        n, k, _ = sh.shape
        field = UsdVol.ParticleField3DGaussianSplat.Define(stage, path)
        field.CreateOpacitiesAttr(Vt.FloatArray.FromNumpy(opacities))
        field.CreateRadianceSphericalHarmonicsDegreeAttr(sh_degree(k))
        field.CreateRadianceSphericalHarmonicsCoefficientsAttr(
            Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(sh.reshape(n * k, 3), dtype=np.float32)))
        UsdGeom.PrimvarsAPI(field).CreatePrimvar(
            "displayColor", Sdf.ValueTypeNames.Color3fArray,
            UsdGeom.Tokens.vertex).Set(Vt.Vec3fArray.FromNumpy(colors))
        self.positions = field.CreatePositionsAttr().GetPath()
        # Half precision (~5e-4, a rotation error no splat shows) halves this attribute,
        # and in fmt="both" the crate stores it once with the instancer's equal quath array.
        self.orientations = field.CreateOrientationshAttr().GetPath()
        self.scales = field.CreateScalesAttr().GetPath()
        self.extent = field.CreateExtentAttr().GetPath()
        # sigmas -> (the splats' support radii, the sigmas' Vt array)
        self._scales = Held(lambda s: (s * np.float32(SPLAT_SUPPORT_SIGMAS), Vt.Vec3fArray.FromNumpy(s)))

    def first_frame_defaults(self, positions: np.ndarray, quats: np.ndarray,
                             sigmas: np.ndarray, xyzw16: np.ndarray) -> list[tuple[Sdf.Path, object]]:
        return []

    def samples(self, positions: np.ndarray, quats: np.ndarray,
                sigmas: np.ndarray, xyzw16: np.ndarray) -> list[tuple[Sdf.Path, object]]:
        """Time samples for one frame: positions [N,3] f32, quats [N,4] wxyz (any length),
        sigmas [N,3], xyzw16 [N,4] the unit quaternions as written (_geom.unit_xyzw_half)."""
        support, scales_vt = self._scales(sigmas)
        box = ellipsoid_extent(positions, quats, support)
        return [
            (self.positions, Vt.Vec3fArray.FromNumpy(positions)),
            (self.orientations, Vt.QuathArray.FromNumpy(xyzw16)),
            (self.scales, scales_vt),
            (self.extent, Vt.Vec3fArray.FromNumpy(box)),
        ]
