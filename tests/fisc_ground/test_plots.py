"""Specification of the map figures and plotting helpers (PNG files, XZ slicing)."""

import numpy as np
import pytest
from matplotlib import image as mpimg

from fisc_agent.map.codec import decode_map, encode_map
from fisc_ground.fields.metrics import centreline_profiles
from fisc_ground.figures.plots import (
    design_tunnel_wall,
    plot_centreline,
    plot_centreline_profiles,
    plot_density_with_vectors,
    plot_map_figures,
    plot_swarm_snapshot,
    plot_xz_comparison,
    xz_slice,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def tiny_map(nx=6, n=4, l=0.5, n_max=10, density=True, x0=0.0):
    """A small synthetic, verified CommandMap on a grid with the axis on cell faces."""
    origin = np.array([x0, -n * l / 2, -n * l / 2])
    i, j, k = np.meshgrid(np.arange(nx), np.arange(n), np.arange(n), indexing="ij")
    idx = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1)
    centers = origin + (idx + 0.5) * l
    keep = np.hypot(centers[:, 1], centers[:, 2]) < 1.0  # drop the 4 corner columns
    idx, centers = idx[keep], centers[keep]
    n_cv = idx.shape[0]
    grid_cv = np.full((nx, n, n), -1, dtype=np.int32)
    grid_cv[idx[:, 0], idx[:, 1], idx[:, 2]] = np.arange(n_cv)
    x = centers[:, 0] - x0
    u = 3.0 + 2.0 * np.exp(-((x - 1.5) ** 2))
    tv = np.stack([u, -0.1 * centers[:, 1], -0.1 * centers[:, 2]], axis=1)
    p = -0.6 * u ** 2
    rng = np.random.default_rng(1)
    n_star = rng.integers(2, n_max + 1, n_cv).astype(np.int32)
    fit_v = np.full((n_cv, n_max, 3), np.nan)
    for c in range(n_cv):  # test fixture only
        fit_v[c, :n_star[c]] = tv[c] + rng.normal(scale=0.3, size=(n_star[c], 3))
    arrays = {
        "cv_center_m": centers, "cv_index": idx.astype(np.int32), "grid_cv": grid_cv, "n_star": n_star,
        "fit_velocity_m_s": fit_v, "fit_mean_velocity_m_s": np.nanmean(fit_v, axis=1),
        "fit_pressure": 0.01 * (p - p.min()) + rng.normal(scale=1e-3, size=n_cv), "fit_loss": np.zeros(n_cv),
        "target_velocity_m_s": tv, "target_pressure_gauge_pa": p,
        "target_density_kg_m3": 1.2 - 1e-4 * u if density else np.full(n_cv, np.nan),
        "swarm_pressure_target": 0.01 * (p - p.min()), "node_count": np.full(n_cv, 5, dtype=np.int32),
    }
    meta = {"n_cv": n_cv, "grid": {"origin_m": origin.tolist(), "cell_size_m": l, "shape": [nx, n, n]},
            "n_range": [2, n_max], "scale": 0.5, "kappa": 0.01, "agent_mass_kg": 1.0, "map_version": 1}
    return decode_map(encode_map(meta, arrays))


def assert_png(path, min_bytes=5000):
    assert path.exists(), path
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC
    assert len(data) > min_bytes
    img = mpimg.imread(path)
    assert img.shape[0] > 100 and img.shape[1] > 300
    assert np.ptp(img[..., :3]) > 0.2  # not a blank image


def test_xz_slice_averages_the_two_layers_next_to_the_axis():
    l = 0.5
    # one x column, layers y = -0.75, -0.25, 0.25, 0.75 at z = 0.25
    centers = np.array([[0.25, y, 0.25] for y in (-0.75, -0.25, 0.25, 0.75)])
    values = np.array([100.0, 1.0, 3.0, 100.0])
    x_edges, z_edges, grid = xz_slice(centers, values, l)
    np.testing.assert_allclose(x_edges, [0.0, 0.5])
    np.testing.assert_allclose(z_edges, [0.0, 0.5])
    assert grid.shape == (1, 1) and grid[0, 0] == pytest.approx(2.0)


def test_xz_slice_grid_layout_and_holes():
    cmap = tiny_map()
    c = np.asarray(cmap["cv_center_m"])
    x_edges, z_edges, grid = xz_slice(c, c[:, 0] + 10 * c[:, 2], 0.5)
    assert grid.shape == (4, 6)
    np.testing.assert_allclose(z_edges, [-1.0, -0.5, 0.0, 0.5, 1.0])
    # the y = +-0.25 layers hold all four z cells; value = x + 10 z at each cell centre
    np.testing.assert_allclose(grid[0, 0], 0.25 + 10 * -0.75)
    np.testing.assert_allclose(grid[3, 5], 2.75 + 10 * 0.75)
    vec = xz_slice(c, np.ones((c.shape[0], 2)), 0.5)[2]
    assert vec.shape == (4, 6, 2)


def test_plot_map_figures_writes_the_paper_figures(tmp_path):
    paths = plot_map_figures(tiny_map(), tmp_path / "figs")
    names = [p.name for p in paths]
    assert names == ["velocity_target_vs_fit.png", "pressure_target_vs_fit.png",
                     "density_target_vs_fit.png", "n_star.png"]
    for p in paths:
        assert_png(p)


def test_plot_map_figures_without_reference_density_and_with_explicit_wall(tmp_path):
    paths = plot_map_figures(tiny_map(density=False), tmp_path, wall_radius=lambda x: 1.0 + 0 * x)
    for p in paths:
        assert_png(p)


def test_design_tunnel_wall_only_for_a_consistent_grid():
    wall = design_tunnel_wall(tiny_map())
    assert wall is not None and wall(np.array([0.0]))[0] == pytest.approx(1.5)
    assert design_tunnel_wall(tiny_map(x0=40.0)) is None


def test_generic_helpers_write_pngs(tmp_path):
    cmap = tiny_map()
    c = np.asarray(cmap["cv_center_m"])
    tv = np.asarray(cmap["target_velocity_m_s"])
    u = tv[:, 0]
    p = plot_xz_comparison(c, {"CFD": u / u.max(), "fitted": 0.9 * u / u.max(), "swarm": None}, 0.5,
                           "velocity", tmp_path / "cmp.png", vectors={"CFD": tv})
    assert_png(p)
    assert_png(plot_density_with_vectors(c, np.asarray(cmap["target_density_kg_m3"]), tv, 0.5,
                                         tmp_path / "dens.png"))
    rng = np.random.default_rng(0)
    pos = np.column_stack([rng.uniform(0, 3, 300), rng.uniform(-0.9, 0.9, 300), rng.uniform(-0.9, 0.9, 300)])
    pos[0] = np.nan  # agents without a position are skipped
    assert_png(plot_swarm_snapshot(pos, c, 0.5, 12.5, tmp_path / "snap.png", slab_half_width_m=0.5))
    x = np.linspace(0, 3, 6)
    assert_png(plot_centreline(x, {"CFD": np.sin(x), "swarm": np.cos(x)}, tmp_path / "cl.png"), min_bytes=3000)
    samples = np.full(c.shape[0], 50)
    prof = centreline_profiles(c, u, np.asarray(cmap["target_pressure_gauge_pa"]),
                               np.asarray(cmap["target_density_kg_m3"]), 0.9 * u,
                               np.asarray(cmap["fit_pressure"]), np.asarray(cmap["target_density_kg_m3"]),
                               samples, min_samples=1)
    assert_png(plot_centreline_profiles(prof, tmp_path / "fig10.png"))


def test_plot_xz_comparison_rejects_empty_input(tmp_path):
    with pytest.raises(ValueError, match="no fields"):
        plot_xz_comparison(np.zeros((1, 3)), {}, 0.5, "t", tmp_path / "x.png")
