"""A deterministic procedural plant made of Gaussians, with a region label per Gaussian.

The plant stands on +z in scene units that are metres: a pot (static, z in [0, 0.2]),
a solid stem up to z = 0.75, two leaves and a flower head. Tests, benchmarks and the demo
give each region a known stiffness (see REGION_TRUTH_E) and check what pdtool recovers.
"""
from __future__ import annotations

import numpy as np
import torch

from pd_tool.core.scene import GaussianScene, rgb_to_sh

REGIONS = ("pot", "stem", "leaf", "flower")
# Ground-truth Young's modulus per region (Pa) used by the demo and the recovery benchmark;
# stem and flower differ by 10x or more, as the recovery benchmark requires.
REGION_TRUTH_E = {"pot": 1.0e7, "stem": 3.0e6, "leaf": 5.0e4, "flower": 3.0e5}
REGION_COLORS = {
    "pot": (0.62, 0.32, 0.18),
    "stem": (0.20, 0.55, 0.18),
    "leaf": (0.30, 0.70, 0.25),
    "flower": (0.95, 0.75, 0.15),
}
POT_TOP = 0.2  # metres; everything below is the static pot
STEM_TOP = 0.75  # metres
STEM_RADIUS = 0.05  # metres
# Fractions of the Gaussian budget per region (pot, stem, leaves, flower).
_SHARES = (0.22, 0.28, 0.25, 0.25)


def _random_quats(rng: np.random.Generator, n: int, jitter: float) -> np.ndarray:
    """Unit quaternions (w, x, y, z) close to identity (small random rotations)."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0, jitter, size=n)
    return np.concatenate([np.cos(angle / 2)[:, None], axis * np.sin(angle / 2)[:, None]], axis=1)


def _pot(rng, n):
    # cylinder shell (side) plus the top soil disc
    n_side = int(n * 0.75)
    th = rng.uniform(0, 2 * np.pi, n_side)
    z = rng.uniform(0.0, POT_TOP, n_side)
    r = 0.10 + 0.03 * z / POT_TOP  # slightly flared
    side = np.stack([r * np.cos(th), r * np.sin(th), z], 1)
    n_top = n - n_side
    rr = 0.12 * np.sqrt(rng.uniform(0, 1, n_top))
    th = rng.uniform(0, 2 * np.pi, n_top)
    top = np.stack([rr * np.cos(th), rr * np.sin(th), np.full(n_top, POT_TOP - 0.01)], 1)
    return np.concatenate([side, top])


def _stem(rng, n):
    # a solid slightly curved cylinder from the soil to STEM_TOP; its radius is about one
    # grid cell at the draft/default grids, so that MPM resolves its bending
    z = POT_TOP - 0.02 + rng.uniform(0, 1, n) * (STEM_TOP - POT_TOP + 0.02)
    r = STEM_RADIUS * np.sqrt(rng.uniform(0, 1, n))
    th = rng.uniform(0, 2 * np.pi, n)
    return np.stack([r * np.cos(th) + _stem_bend(z), r * np.sin(th), z], 1)


def _stem_bend(z):
    """The stem axis's offset along +x at height z (metres)."""
    t = (np.asarray(z) - (POT_TOP - 0.02)) / (STEM_TOP - POT_TOP + 0.02)
    return 0.03 * t ** 2


LEAF_THICKNESS = 0.02  # metres: the plant's leaves, as the tests and fit benchmarks use it
PETAL_THICKNESS = 0.04  # metres: its flower head
THIN_THICKNESS = 0.003  # metres: leaves and petals of the thin plant, as real ones are


# rooted parts reach this far into the stem (metres): a thin leaf or petal that only
# touches its stem comes apart from it on a grid fine enough to resolve it (a cell's gap
# separates MPM particles), and then flies off under a push
ROOT_DEPTH = 0.01


def _leaves(rng, n, thickness=LEAF_THICKNESS, rooted=False):
    """Two leaves. rooted: each starts ROOT_DEPTH inside the stem, on its bent axis (thin
    leaves); else at the straight axis's radius, which leaves one 1.3 cm off the bent stem:
    a 2 cm leaf still overlaps it within a cell at the grids it is simulated on."""
    out = []
    for k, (zc, ang) in enumerate(((0.42, 0.3), (0.56, 0.3 + np.pi))):
        m = n // 2 if k == 0 else n - n // 2
        # an ellipse 16 cm x 6 cm, rising 25 degrees, `thickness` thick
        u = rng.uniform(0, 1, m)
        v = rng.uniform(-1, 1, m) * np.sqrt(np.clip(1 - (2 * u - 1) ** 2, 0, 1))
        root = STEM_RADIUS - ROOT_DEPTH if rooted else STEM_RADIUS
        along = root + (0.16 + STEM_RADIUS - root) * u
        across = 0.03 * v
        up = along * np.tan(np.radians(25)) + rng.uniform(-thickness / 2, thickness / 2, m)
        c, s = np.cos(ang), np.sin(ang)
        x0 = float(_stem_bend(zc)) if rooted else 0.0
        out.append(np.stack([x0 + along * c - across * s, along * s + across * c, zc + up], 1))
    return np.concatenate(out)


def _flower(rng, n, thickness=PETAL_THICKNESS, rooted=False):
    """A flat head: a disc of petals of radius 13 cm, `thickness` thick, cupped. Its
    underside rests on the stem's top; rooted: ROOT_DEPTH below it, so that a thin
    head holds on to its stem."""
    rr = 0.13 * np.sqrt(rng.uniform(0, 1, n))
    th = rng.uniform(0, 2 * np.pi, n)
    base = STEM_TOP - ROOT_DEPTH if rooted else STEM_TOP
    z = base + thickness / 2 + rng.uniform(-thickness / 2, thickness / 2, n) + 0.15 * rr
    return np.stack([rr * np.cos(th) + 0.03, rr * np.sin(th), z], 1)


def _scene(pos, quats, scales, opacities, sh, labels, names, device) -> GaussianScene:
    """A synthetic GaussianScene from numpy arrays (float32 tensors on `device`)."""
    def t(a):
        return torch.as_tensor(a, dtype=torch.float32, device=device)

    return GaussianScene(positions=t(pos), quats=t(quats), scales=t(scales), opacities=t(opacities), sh=t(sh),
                         source_format="synthetic", labels=labels, label_names=names)


def make_plant(n: int = 4000, seed: int = 0, sh_degree: int = 0, device: str | torch.device = "cpu",
               thin: bool = True) -> GaussianScene:
    """The procedural plant with about `n` Gaussians (exactly n), seeded and deterministic.

    thin: leaves and petals THIN_THICKNESS thick (a real plant's), far below a cell at the
    draft and default grids: the hard case, and the default; False: 2 and 4 cm, which MPM
    nearly resolves (the speed benchmarks, and fits judged on their own discretisation).
    Returns a GaussianScene whose `labels` [n] index REGIONS and whose `label_names` is
    REGIONS. Scene units are metres, +z is up, the pot is below z = POT_TOP.
    """
    if n < 100:
        raise ValueError("make_plant needs at least 100 Gaussians")
    rng = np.random.default_rng(seed)
    counts = [int(n * s) for s in _SHARES]
    counts[-1] = n - sum(counts[:-1])
    leaf_t, petal_t = (THIN_THICKNESS, THIN_THICKNESS) if thin else (LEAF_THICKNESS, PETAL_THICKNESS)
    # drawn in this order from one generator: the plant of a seed stays the same
    parts = [_pot(rng, counts[0]), _stem(rng, counts[1]), _leaves(rng, counts[2], leaf_t, rooted=thin),
             _flower(rng, counts[3], petal_t, rooted=thin)]
    pos = np.concatenate(parts)
    labels = np.concatenate([np.full(c, i, np.int32) for i, c in enumerate(counts)])
    # splat size from the local spacing of each region: about half the mean neighbour gap
    scales = np.empty((n, 3))
    colors = np.empty((n, 3))
    for i, name in enumerate(REGIONS):
        sel = labels == i
        ext = np.ptp(pos[sel], axis=0).clip(0.01, None)
        spacing = (np.prod(ext) / sel.sum()) ** (1 / 3)
        scales[sel] = spacing * 0.6 * rng.uniform(0.7, 1.3, size=(sel.sum(), 3))
        base = np.array(REGION_COLORS[name])
        colors[sel] = np.clip(base + rng.normal(0, 0.04, size=(sel.sum(), 3)), 0, 1)
    quats = _random_quats(rng, n, jitter=np.pi)
    sh = np.zeros((n, (sh_degree + 1) ** 2, 3))
    sh[:, 0] = rgb_to_sh(torch.from_numpy(colors)).numpy()
    opac = rng.uniform(0.7, 0.95, n)
    return _scene(pos, quats, scales, opac, sh, labels, REGIONS, device)


def driver_regions(scene: GaussianScene, prep, drivers) -> np.ndarray:
    """Each driver's region (index into REGIONS): the one most of its Gaussians belong to.
    scene: the plant (its .labels); prep, drivers: a PreparedScene and its drivers."""
    member = drivers.labels.cpu().numpy()[: prep.count]
    votes = np.zeros((len(drivers.positions), len(REGIONS)))
    np.add.at(votes, (member, scene.labels[prep.foreground]), 1.0)
    return votes.argmax(axis=1)


def driver_truth_E(scene: GaussianScene, prep, drivers) -> np.ndarray:
    """Each driver's true E (Pa): that of its region (driver_regions)."""
    return np.array([REGION_TRUTH_E[n] for n in REGIONS])[driver_regions(scene, prep, drivers)]


STRIP_REGIONS = ("base", "strip")


def make_strip(n: int = 4000, *, length: float = 0.8, width: float = 0.3, thickness: float = 0.02,
               base: float = 0.1, seed: int = 0, device: str | torch.device = "cpu") -> GaussianScene:
    """A thin strip standing on a block: the analytic thin case of the convergence benchmark.

    The strip rises along +z from z = 0 to `length`, `width` along y and `thickness` along x
    (metres), filled uniformly; the block below z = 0 (`base` deep, wider than the strip)
    is meant to be static, which clamps the strip's foot. Labels index STRIP_REGIONS.
    """
    rng = np.random.default_rng(seed)
    n_base = max(n // 8, 10)
    n_strip = n - n_base
    strip = np.stack([rng.uniform(-thickness / 2, thickness / 2, n_strip), rng.uniform(-width / 2, width / 2, n_strip),
                      rng.uniform(0.0, length, n_strip)], 1)
    block = np.stack([rng.uniform(-width / 2, width / 2, n_base), rng.uniform(-width / 2, width / 2, n_base),
                      rng.uniform(-base, 0.0, n_base)], 1)
    pos = np.concatenate([block, strip])
    labels = np.concatenate([np.zeros(n_base, np.int32), np.ones(n_strip, np.int32)])
    spacing = (length * width * thickness / n_strip) ** (1 / 3)
    scales = np.full((n, 3), 0.5 * spacing)
    colors = np.where(labels[:, None] == 0, [0.5, 0.5, 0.5], [0.3, 0.7, 0.25])
    return _scene(pos, np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), scales, np.full(n, 0.9),
                  rgb_to_sh(torch.from_numpy(colors))[:, None].numpy(), labels, STRIP_REGIONS, device)


def clamped_strip_frequency(E: float, nu: float, density: float, length: float, thickness: float) -> float:
    """First bending frequency (Hz) of a clamped-free strip, Kirchhoff plate theory:
    f1 = 1.8751^2 / (2 pi L^2) sqrt(D / (rho t)), D = E t^3 / (12 (1 - nu^2)). SI units."""
    D = E * thickness ** 3 / (12.0 * (1.0 - nu ** 2))
    return 1.8751 ** 2 / (2.0 * np.pi * length ** 2) * float(np.sqrt(D / (density * thickness)))


def make_block(n: int, res: int, seed: int = 0, E: float = 1.0e5,
               density: float = 1000.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An elastic block of n simulation particles for a res^3 grid over the unit box: the
    MPM speed benchmarks' scene, given straight to MPMSolver or DiffSim.

    The particles lie uniformly at random (seeded) in a cube centred at (0.5, 0.5, 0.5) m,
    sized so that an occupied cell holds about 8 (at most 0.6 m a side), in random order;
    a thin layer at the bottom is static (a clamp). Returns (x [n, 3] float32 m,
    volume [n] m^3, mass [n] kg, E [n] Pa, static [n] bool).
    """
    rng = np.random.default_rng(seed)
    side = min(0.6, (n / 8.0) ** (1.0 / 3.0) / res)
    x = 0.5 + (rng.random((n, 3)) - 0.5) * side
    vol = np.full(n, side ** 3 / n)
    static = x[:, 2] < 0.5 - 0.45 * side
    return x.astype(np.float32), vol, vol * density, np.full(n, float(E)), static


def make_splat_ball(n: int, seed: int = 0, scale_factor: float = 1.0,
                    device: str | torch.device = "cpu") -> GaussianScene:
    """n random Gaussians in a ball of radius 1 (scene units), the rasteriser benchmarks'
    scene: centres uniform in the ball, random rotations, scales log-uniform in
    [0.005, 0.04] times `scale_factor` (to keep the pixel coverage alike across counts),
    opacities uniform in [0.1, 0.9], SH degree 3 (sh [n, 16, 3]). Seeded (torch's
    generator), float32 tensors on `device`; no labels."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g)
    d = d / d.norm(dim=1, keepdim=True)
    means = d * torch.rand(n, 1, generator=g) ** (1.0 / 3.0)
    quats = torch.randn(n, 4, generator=g)
    quats = quats / quats.norm(dim=1, keepdim=True)
    log_s = torch.empty(n, 3).uniform_(float(np.log(0.005)), float(np.log(0.04)), generator=g)
    opacities = torch.rand(n, generator=g) * 0.8 + 0.1
    sh = torch.randn(n, 16, 3, generator=g) * 0.2
    sh[:, 0] = torch.randn(n, 3, generator=g) * 0.8
    return GaussianScene(positions=means.to(device), quats=quats.to(device),
                         scales=(torch.exp(log_s) * scale_factor).to(device), opacities=opacities.to(device),
                         sh=sh.to(device), source_format="synthetic")
