"""Local thickness of the moving parts and the thin-part notice of bake, fit and select."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from pd_tool.prepare import thickness as T


def _slab(n: int, t: float, side: float, rng) -> np.ndarray:
    return np.stack([rng.uniform(0, side, n), rng.uniform(0, side, n), rng.uniform(0, t, n)], 1) + 0.37


def test_window_moments_match_the_brute_force_twin(device) -> None:
    """The fixed-point window sums on each device against each particle's window gathered
    explicitly, with unit weights and with weights spread over 30x."""
    rng = np.random.default_rng(1)
    x = np.concatenate([_slab(1500, 0.01, 0.4, rng), rng.uniform(0.2, 0.5, (800, 3))])
    for w in (None, rng.uniform(0.1, 3.0, len(x))):
        fast, ref = T.local_thickness(x, 0.06, w, device=device), T.local_thickness_ref(x, 0.06, w)
        assert np.array_equal(np.isnan(fast), np.isnan(ref))
        assert np.isfinite(fast).sum() > 1000
        np.testing.assert_allclose(fast[np.isfinite(fast)], ref[np.isfinite(ref)], rtol=1e-9, atol=1e-12)


def test_smallest_eigenvalue_matches_lapack(device) -> None:
    """The closed form against LAPACK's: random covariances, flat and needle-like ones,
    repeated eigenvalues, multiples of the identity and zeros."""
    rng = np.random.default_rng(9)
    q, _ = np.linalg.qr(rng.normal(size=(400, 3, 3)))
    lam = rng.uniform(0, 1, (400, 3)) * np.array([1.0, 1.0, 1.0])
    lam[:100, 0] *= 1e-6  # flat
    lam[100:200, :2] *= 1e-4  # needles
    lam[200:250, 1] = lam[200:250, 0]  # repeated
    lam[250:260] = 0.7
    lam[260:265] = 0.0
    cov = np.einsum("kij,kj,klj->kil", q, lam, q)
    cov = 0.5 * (cov + cov.transpose(0, 2, 1))
    got = T.smallest_eigenvalue(torch.as_tensor(cov, device=device)).cpu().numpy()
    want = np.linalg.eigvalsh(cov)[:, 0]
    scale = np.abs(cov).max()
    single = np.ones(len(cov), bool)
    single[100:250] = False  # two eigenvalues (nearly) coincide: the cubic's root is sqrt(eps)-sensitive
    np.testing.assert_allclose(got[single], want[single], rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(got[~single], want[~single], rtol=0, atol=1e-7 * scale)


@pytest.mark.parametrize("t", [0.002, 0.01, 0.03])
def test_a_slab_reads_its_own_thickness(t: float) -> None:
    x = _slab(40000, t, 0.6, np.random.default_rng(2))
    assert np.nanmedian(T.local_thickness(x, 0.06)) == pytest.approx(t, rel=0.05)


def test_a_filled_block_reads_about_its_window_and_a_rod_most_of_its_diameter() -> None:
    rng = np.random.default_rng(3)
    block = rng.uniform(0, 0.6, (200000, 3))
    # the smallest eigenvalue of a sample covariance reads a little low
    assert 0.85 * 0.06 < np.nanmedian(T.local_thickness(block, 0.06)) <= 0.06
    th, r = rng.uniform(0, 2 * np.pi, 20000), 0.01 * np.sqrt(rng.uniform(0, 1, 20000))
    rod = np.stack([r * np.cos(th), r * np.sin(th), rng.uniform(0, 0.6, 20000)], 1)
    assert np.nanmedian(T.local_thickness(rod, 0.06)) == pytest.approx(0.87 * 0.02, rel=0.1)


def test_sparse_windows_have_no_estimate() -> None:
    x = np.random.default_rng(4).uniform(0, 10, (50, 3))
    assert np.isnan(T.local_thickness(x, 0.06)).all()
    assert T.thin_parts(x, np.ones(50, bool), 0.06, 32) is None


def _sphere(n: int, radius: float, rng) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def test_a_sheet_is_thin_and_a_scanned_ball_a_few_cells_wide_is_not() -> None:
    rng = np.random.default_rng(5)
    sheet = _slab(30000, 0.003, 0.6, rng)
    found = T.thin_parts(sheet, np.ones(len(sheet), bool), 0.05, 32)
    assert found is not None and found.thin and found.share > 0.9
    assert found.thickness_m == pytest.approx(0.003, rel=0.1)
    # a scan samples a bulk part on its surface only: thin within one cell, not within three
    # (two balls 0.8 m apart: the object is large enough for the three-cell window)
    ball = _sphere(30000, 0.1, rng)
    assert np.nanmedian(T.local_thickness(ball, 0.05)) < 0.025
    ball = np.concatenate([ball, ball + [0.8, 0.0, 0.0]])
    found = T.thin_parts(ball, np.ones(len(ball), bool), 0.05, 32)
    assert found is not None and not found.thin, found


def test_thin_mask_marks_the_sheet_not_the_block_nor_the_static() -> None:
    """Each particle's verdict, counted as ThinParts counts them: a 3 mm sheet beside a
    filled block 0.2 m wide; the sheet's particles are thin, the block's not, and a static
    particle never is."""
    rng = np.random.default_rng(7)
    sheet = _slab(20000, 0.003, 0.6, rng)
    block = rng.uniform(0.0, 0.2, (20000, 3)) + [1.2, 0.37, 0.37]
    x = np.concatenate([sheet, block])
    moving = np.ones(len(x), bool)
    moving[:500] = False
    mask = T.thin_mask(x, moving, 0.05)
    assert mask.shape == (len(x),) and mask.dtype == bool
    assert not mask[:500].any()
    assert mask[500:20000].mean() > 0.9 and mask[20000:].mean() < 0.02
    found = T.thin_parts(x, moving, 0.05, 32)
    assert found.share == pytest.approx(mask[moving].mean(), abs=1e-12)


def test_static_particles_are_not_judged() -> None:
    sheet = _slab(20000, 0.003, 0.6, np.random.default_rng(6))
    found = T.thin_parts(sheet, np.zeros(len(sheet), bool), 0.05, 32)
    assert found is None


def test_the_line_names_thickness_cell_and_the_quality_that_resolves() -> None:
    from pd_tool.materials.presets import builtin

    grids = {name: int(q["grid_res"]) for name, q in builtin("quality").items()}
    near = T.ThinParts(share=0.3, thickness_m=0.02, dx_m=0.06, grid_needed=grids["default"] - 1)
    line = near.line(32)
    assert "\n" not in line and "30%" in line and "2 cm" in line and "6 cm" in line
    assert line.endswith("try --quality default or finer"), line
    assert T.ThinParts(0.3, 0.01, 0.06, grids["final"]).line(32).endswith("try --quality final or finer")
    mid = T.ThinParts(share=0.3, thickness_m=0.005, dx_m=0.06, grid_needed=grids["final"] + 20)
    assert mid.line(32).endswith(f"a --quality file with grid_res = {grids['final'] + 20} or more")
    far = T.ThinParts(share=0.3, thickness_m=0.003, dx_m=0.06, grid_needed=640)
    assert "beyond the 256" in far.line(32) and "3 mm" in far.line(32)


def test_prepare_reports_thin_leaves_and_the_quality_to_try() -> None:
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
    from pd_tool.io.synthetic import POT_TOP, make_plant

    thin = prepare_scene(make_plant(6000, thin=True), PrepareOptions(static_below=POT_TOP, grid_res=48))
    lines = [line for line in thin.report if line.startswith("thin parts:")]
    assert len(lines) == 1 and " mm thick" in lines[0], thin.report  # 3 mm leaves and petals
    # the 2 cm leaves are thin at 16 cells, and not at the quality the line names
    coarse = prepare_scene(make_plant(20000, thin=False), PrepareOptions(static_below=POT_TOP, grid_res=16))
    line = next(line for line in coarse.report if line.startswith("thin parts:"))
    named = line.split("--quality ")[1].split()[0]
    from pd_tool.materials.presets import load_preset

    grid = int(load_preset("quality", named)["grid_res"])
    fine = prepare_scene(make_plant(20000, thin=False), PrepareOptions(static_below=POT_TOP, grid_res=grid))
    assert not any(line.startswith("thin parts:") for line in fine.report), fine.report


@pytest.mark.parametrize("grid", [16, 64])
def test_the_thin_plant_reads_its_leaves_thickness_or_an_upper_bound(grid: int) -> None:
    """A fine cell's window holds only the leaf: it reads the leaf's 3 mm. A 15 cm cell's
    can take in the stem beside it too: it reads more, never less, and under a quarter cell."""
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
    from pd_tool.io.synthetic import POT_TOP, THIN_THICKNESS, make_plant

    prep = prepare_scene(make_plant(20000, thin=True), PrepareOptions(static_below=POT_TOP, grid_res=grid))
    found = T.thin_parts(prep.positions_sim, ~prep.static, prep.dx, max(prep.grid_dims), prep.volumes)
    assert found is not None and found.thin
    if grid == 64:
        assert found.thickness_m == pytest.approx(THIN_THICKNESS, rel=0.25)
    else:
        assert 0.9 * THIN_THICKNESS < found.thickness_m < T.RESOLVED_CELLS * prep.dx


def test_a_line_of_particles_reads_zero_and_the_line_still_forms() -> None:
    x = np.zeros((1600, 3)) + 0.5
    x[:, 2] = np.linspace(0.1, 0.9, 1600)
    t = T.local_thickness(x, 0.05)
    assert np.isfinite(t).sum() > 1500 and np.nanmax(t) < 1e-9  # an end's window can be too sparse
    assert np.isnan(T.local_thickness(x, 0.0)).all()
    found = T.thin_parts(x, np.ones(len(x), bool), 0.05, 32)
    assert found is not None and found.thin and "\n" not in found.line(32)


def test_refine_for_thin_raises_the_grid_to_resolve_thin_leaves_within_the_ceiling() -> None:
    from pd_tool.prepare.preparation import MIN_PARTICLES_PER_CELL, PrepareOptions, prepare_scene, refine_for_thin
    from pd_tool.io.synthetic import POT_TOP, make_plant

    coarse = prepare_scene(make_plant(20000, thin=True), PrepareOptions(static_below=POT_TOP, grid_res=32))
    assert coarse.thin is not None and coarse.thin.thin
    capped = refine_for_thin(coarse, 48)
    assert capped is not None and capped.options.grid_res == 48 and capped.thin.thin
    line = capped.report[-1]
    assert line.startswith("thin parts:") and "the most this quality allows" in line and "keeps 32" in line
    assert sum(r.startswith("thin parts:") for r in capped.report) == 1, capped.report
    # as fine as the reading asks (rounded up to 16), unless the particles no longer fill it
    full = refine_for_thin(coarse, 256)
    asked = 16 * -(-coarse.thin.grid_needed // 16)
    g = full.options.grid_res
    assert 48 < g <= asked and g % 16 == 0
    assert full.n_particles >= MIN_PARTICLES_PER_CELL * full.occupied_cells()
    if g < asked:  # the next grid up would hold fewer particles per cell than the floor
        from pd_tool.prepare.preparation import cell_size

        nxt = cell_size(full.object_size_m, full.options.padding, g + 16)[0]
        assert full.n_particles < MIN_PARTICLES_PER_CELL * full.occupied_cells(nxt)
    assert full.dx < capped.dx < coarse.dx
    assert refine_for_thin(coarse, 32) is None  # no room to grow


def _plant_with_a_floating_flower(gap: float, n: int = 20000):
    """The thin plant with its flower head lifted `gap` m off the stem."""
    from pd_tool.io.synthetic import REGIONS, make_plant

    scene = make_plant(n, thin=True)
    flower = torch.as_tensor(scene.labels == REGIONS.index("flower"))
    scene.positions[flower, 2] += gap
    return scene, float(flower.float().mean())


def test_the_thin_plant_holds_together_on_fine_grids() -> None:
    from pd_tool.prepare.preparation import PrepareOptions, cell_size, prepare_scene
    from pd_tool.io.synthetic import POT_TOP, make_plant

    prep = prepare_scene(make_plant(20000, thin=True), PrepareOptions(static_below=POT_TOP, grid_res=32))
    for grid in (32, 64, 128):  # its leaves and flower reach into the stem
        assert prep.detached_share(cell_size(prep.object_size_m, prep.options.padding, grid)[0]) < 0.002, grid
    assert not any(r.startswith("loose parts") for r in prep.report)


def test_a_finer_grid_that_would_tear_a_part_off_is_not_taken() -> None:
    from pd_tool.prepare.preparation import MAX_MORE_DETACHED, PrepareOptions, prepare_scene, refine_for_thin
    from pd_tool.io.synthetic import POT_TOP

    scene, share = _plant_with_a_floating_flower(0.04)  # under a 32-cell cell, over two 96-cell ones
    coarse = prepare_scene(scene, PrepareOptions(static_below=POT_TOP, grid_res=32))
    assert coarse.thin is not None and coarse.thin.thin and coarse.detached_share() < 0.002
    finer = refine_for_thin(coarse, 256)
    if finer is None:
        assert coarse.report[-1].startswith("thin parts: kept the 32-cell grid: a finer one leaves")
        assert "--static-box" in coarse.report[-1]
    else:  # raised only as far as the flower stays on
        assert finer.options.grid_res < 96 and finer.detached_share() <= MAX_MORE_DETACHED
    torn = prepare_scene(scene, PrepareOptions(static_below=POT_TOP, grid_res=128))
    moving = ~np.asarray(torn.static, bool)
    assert torn.detached_share() == pytest.approx(share * len(moving) / moving.sum(), abs=0.02)  # the flower
    line = [r for r in torn.report if r.startswith("loose parts:")]
    assert len(line) == 1 and f"{torn.detached_share():.0%}" in line[0] and "--foreground-box" in line[0]
    # `pdtool select` paints the loose flower orange, and only it
    from pd_tool.io.synthetic import REGIONS
    from pd_tool.prepare.selection import LOOSE_RGB, selection_scene

    rgb = selection_scene(torn).colors.numpy()
    orange = np.abs(rgb - np.asarray(LOOSE_RGB)).max(axis=1) < 1e-3
    flower = scene.labels == REGIONS.index("flower")
    assert orange[flower].mean() > 0.98 and not orange[~flower].any()


def test_a_scene_too_sparse_for_a_finer_grid_keeps_its_own() -> None:
    from pd_tool.prepare.preparation import MIN_PARTICLES_PER_CELL, PrepareOptions, cell_size, prepare_scene, refine_for_thin
    from pd_tool.io.synthetic import POT_TOP, make_plant

    sparse = prepare_scene(make_plant(2500, thin=True), PrepareOptions(static_below=POT_TOP, grid_res=48))
    assert sparse.thin is not None and sparse.thin.thin and sparse.thin.grid_needed > 64
    finer = cell_size(sparse.object_size_m, sparse.options.padding, 64)[0]
    assert sparse.n_particles < MIN_PARTICLES_PER_CELL * sparse.occupied_cells(finer)  # 64 cells: too sparse
    assert refine_for_thin(sparse, 256) is None
    assert sparse.report[-1].startswith("thin parts: kept the 48-cell grid") and "denser capture" in sparse.report[-1]


def test_a_floor_of_drivers_a_cell_clusters_them_from_sub_particles() -> None:
    """A thin plant of 3,000 Gaussians on 64 cells holds under 8 drivers in each cell its
    moving particles occupy at the ratio 0.05: the floor clusters 8 a cell from the
    Gaussians' sub-particles, keeps the mass and hangs every particle on its nearest."""
    from pd_tool.prepare.preparation import MIN_DRIVERS_PER_CELL, PrepareOptions, prepare_scene
    from pd_tool.io.synthetic import POT_TOP, make_plant

    prep = prepare_scene(make_plant(3000, thin=True), PrepareOptions(static_below=POT_TOP, grid_res=64))
    moving = prep.moving_cells()
    plain = prep.build_drivers(ratio=0.05)
    assert not prep.splits(0.05, 0) and prep.splits(0.05, MIN_DRIVERS_PER_CELL)
    floor = prep.build_drivers(ratio=0.05, min_per_cell=MIN_DRIVERS_PER_CELL)
    n_moving = int((~floor.static).sum())
    assert n_moving >= 0.9 * MIN_DRIVERS_PER_CELL * moving > 2 * int((~plain.static).sum())
    assert floor.mass.double().sum().item() == pytest.approx(prep.masses.sum(), rel=1e-5)
    assert floor.static.any() and len(floor.labels) == prep.n_particles
    d = ((floor.points_rest[:, None, :] - floor.positions[None, :, :]) ** 2).sum(-1)
    assert torch.equal(floor.labels, d.argmin(1)) or torch.allclose(
        d.gather(1, floor.labels[:, None])[:, 0], d.min(1).values)
    # the estimates' count is the clustering's: the sub-particles spread over each Gaussian's
    # extent and cross more cells than the Gaussians' centres
    assert prep.split_count(MIN_DRIVERS_PER_CELL) > 1.2 * MIN_DRIVERS_PER_CELL * moving
    assert prep.floor_ratio(0.05, MIN_DRIVERS_PER_CELL) * prep.n_particles == pytest.approx(n_moving, rel=0.02)
    # a ratio that already gives the floor is kept as it is
    assert not prep.splits(1.0, 1.0) and prep.floor_ratio(1.0, 1.0) == 1.0


def test_refine_for_thin_leaves_a_scene_without_thin_parts_alone() -> None:
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene, refine_for_thin
    from pd_tool.io.synthetic import POT_TOP, make_plant

    thick = prepare_scene(make_plant(6000, thin=False), PrepareOptions(static_below=POT_TOP, grid_res=48))  # 2 cm leaves
    assert thick.thin is None or not thick.thin.thin
    assert refine_for_thin(thick, 256) is None
