"""Specification of the cubic CV partition (DESIGN.md section 2, paper "Spatial Partitioning")."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fisc_ground.fit.partition import ControlVolumes, cell_of, grid_origin_and_shape, partition, partition_field
from fisc_ground.reference.field import ReferenceField



def _read_fluent_export(path: Path) -> dict[str, np.ndarray]:
    """Tiny local reader of the Fluent node export (keeps these tests independent of the importer)."""
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    return {
        "points": data[:, 1:4],
        "pressure": data[:, 4],
        "density": data[:, 5],
        "velocity": data[:, 6:9],
    }


@pytest.fixture(scope="module")
def reference_nodes(shared_path) -> dict[str, np.ndarray]:
    return _read_fluent_export(shared_path("reference", "cd_nozzle_inviscid", "fluent_export_3d.csv"))


def _partition_oracle(points, values, cell_size, min_nodes=1):
    """Plain-Python oracle: apply the written rules node by node, then average per cell."""
    l = cell_size
    x0 = min(p[0] for p in points)
    y0 = math.floor(min(p[1] for p in points) / l + 1e-6) * l
    z0 = math.floor(min(p[2] for p in points) / l + 1e-6) * l
    origin = (x0, y0, z0)
    shape = []
    for a in range(3):
        hi = max(p[a] for p in points)
        shape.append(max(1, math.ceil((hi - origin[a]) / l - 1e-6)))
    cells: dict[tuple[int, int, int], list[int]] = {}
    for n, p in enumerate(points):
        idx = []
        for a in range(3):
            i = math.floor((p[a] - origin[a]) / l + 1e-6)
            if i == shape[a]:  # on the upper extent: fold into the last slice
                i -= 1
            idx.append(i)
        cells.setdefault(tuple(idx), []).append(n)
    keys = sorted(k for k, v in cells.items() if len(v) >= min_nodes)
    means = np.array([np.mean(values[cells[k]], axis=0) for k in keys])
    counts = np.array([len(cells[k]) for k in keys])
    return np.array(origin), tuple(shape), np.array(keys), counts, means


def _lattice(x_lo, x_hi, y_lo, y_hi, z_lo, z_hi, h):
    xs = np.arange(round((x_hi - x_lo) / h) + 1) * h + x_lo
    ys = np.arange(round((y_hi - y_lo) / h) + 1) * h + y_lo
    zs = np.arange(round((z_hi - z_lo) / h) + 1) * h + z_lo
    return np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)


def test_grid_starts_at_inlet_plane_and_puts_the_axis_on_cell_faces():
    pts = _lattice(0.3, 2.3, -0.9, 0.9, -0.4, 0.7, 0.1)
    origin, shape = grid_origin_and_shape(pts, 0.5)
    assert origin[0] == pytest.approx(0.3)  # x from the inlet plane, not snapped
    assert origin[1] == pytest.approx(-1.0)  # floor(-0.9 / 0.5) * 0.5
    assert origin[2] == pytest.approx(-0.5)
    # the axis y = 0, z = 0 is a face: (0 - origin) / l is an integer
    assert ((0.0 - origin[1:]) / 0.5) == pytest.approx(np.round((0.0 - origin[1:]) / 0.5))
    # x: 2.0 m of data = 4 cells exactly (outlet nodes fold, no 5th slice); y: [-1, 0.9] -> 4; z: [-0.5, 0.7] -> 3
    assert shape == (4, 4, 3)


def test_half_open_cells_and_outlet_plane_folding():
    l = 0.5
    origin = np.array([0.0, -1.0, -1.0])
    shape = (4, 4, 4)
    pts = np.array(
        [
            [0.5, 0.0, 0.0],  # on faces -> upper cell
            [0.49, -0.01, -0.01],  # just below the faces -> lower cell
            [2.0, 1.0, 1.0],  # on the grid's upper faces -> folded into the last cell
            [2.2, 0.0, 0.0],  # beyond the grid -> out-of-range index, not folded
            [-0.1, 0.0, 0.0],  # before the grid -> negative
            [0.5 - 1e-9, 0.0, 0.0],  # round-off below a face counts as on the face
        ]
    )
    ijk = cell_of(pts, origin, l, shape)
    np.testing.assert_array_equal(
        ijk, [[1, 2, 2], [0, 1, 1], [3, 3, 3], [4, 2, 2], [-1, 2, 2], [1, 2, 2]]
    )


def test_partition_matches_a_plain_python_oracle_on_a_lattice_with_face_nodes():
    rng = np.random.default_rng(3)
    # lattice of spacing 0.1 (nodes on every face) inside a cylinder, plus random scattered nodes
    lat = _lattice(0.0, 3.0, -1.2, 1.2, -1.2, 1.2, 0.1)
    lat = lat[np.hypot(lat[:, 1], lat[:, 2]) <= 1.2 - 0.1 * lat[:, 0]]
    pts = np.concatenate([lat, rng.uniform([0, -1, -1], [3, 1, 1], size=(500, 3))])
    vel = rng.normal(size=(pts.shape[0], 3))
    prs = rng.normal(size=pts.shape[0]) * 50
    rho = 1.2 + rng.normal(size=pts.shape[0]) * 0.01
    for min_nodes in (1, 4):
        cv = partition(pts, vel, prs, rho, cell_size_m=0.5, min_nodes=min_nodes)
        values = np.concatenate([vel, prs[:, None], rho[:, None]], axis=1)
        origin, shape, keys, counts, means = _partition_oracle(list(map(tuple, pts)), values, 0.5, min_nodes)
        np.testing.assert_allclose(cv.origin_m, origin)
        assert cv.shape == shape
        np.testing.assert_array_equal(cv.index, keys)
        np.testing.assert_array_equal(cv.node_count, counts)
        np.testing.assert_allclose(cv.target_velocity_m_s, means[:, :3], atol=1e-12)
        np.testing.assert_allclose(cv.target_pressure_gauge_pa, means[:, 3], atol=1e-10)
        np.testing.assert_allclose(cv.target_density_kg_m3, means[:, 4], atol=1e-12)


def test_contract_fields_order_and_grid_lookup():
    rng = np.random.default_rng(0)
    pts = rng.uniform([0, -1.5, -1.5], [15, 1.5, 1.5], size=(4000, 3))
    cv = partition(pts, rng.normal(size=(4000, 3)), rng.normal(size=4000), None)
    assert isinstance(cv, ControlVolumes)
    assert cv.index.dtype == np.int32 and cv.grid_cv.dtype == np.int32 and cv.node_count.dtype == np.int32
    assert cv.grid_cv.shape == cv.shape
    # lexicographic (i, j, k)
    flat = np.ravel_multi_index(cv.index.T, cv.shape)
    assert np.all(np.diff(flat) > 0)
    # grid_cv is the inverse of index; -1 elsewhere
    np.testing.assert_array_equal(cv.grid_cv[tuple(cv.index.T)], np.arange(cv.n_cv))
    assert np.count_nonzero(cv.grid_cv >= 0) == cv.n_cv
    np.testing.assert_allclose(cv.center_m, cv.origin_m + (cv.index + 0.5) * 0.5)
    assert np.all(np.isnan(cv.target_density_kg_m3))  # no density in the source
    assert cv.node_count.sum() == 4000  # no node lost
    assert cv.cell_volume_m3 == pytest.approx(0.125)


def test_min_nodes_drops_sparse_cells():
    pts = np.array([[0.1, 0.1, 0.1], [0.2, 0.1, 0.1], [0.7, 0.1, 0.1], [1.0, 0.6, 0.2]])
    vel = np.arange(12, dtype=float).reshape(4, 3)
    cv1 = partition(pts, vel, np.zeros(4), None, cell_size_m=0.5, min_nodes=1)
    cv2 = partition(pts, vel, np.zeros(4), None, cell_size_m=0.5, min_nodes=2)
    assert cv1.shape == (2, 2, 1)  # x in [0.1, 1.0]: 0.9 m -> 2 slices; y in [0, 0.6] -> 2
    assert cv1.n_cv == 3 and cv2.n_cv == 1
    np.testing.assert_allclose(cv2.target_velocity_m_s[0], vel[:2].mean(axis=0))
    assert cv2.grid_cv[1, 0, 0] == -1


def test_invalid_input_is_refused_with_a_clear_message():
    pts = np.zeros((3, 3))
    vel = np.zeros((3, 3))
    with pytest.raises(ValueError, match="cell_size_m"):
        partition(pts, vel, np.zeros(3), None, cell_size_m=0.0)
    with pytest.raises(ValueError, match="min_nodes"):
        partition(pts, vel, np.zeros(3), None, min_nodes=0)
    with pytest.raises(ValueError, match="velocity_m_s must have shape"):
        partition(pts, vel[:2], np.zeros(3), None)
    bad = np.zeros(3)
    bad[2] = np.nan
    with pytest.raises(ValueError, match="pressure_gauge_pa has a non-finite value at node 2"):
        partition(pts, vel, bad, None)
    with pytest.raises(ValueError, match="non-empty"):
        partition(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), None)


def test_reference_export_partition(reference_nodes):
    """The shipped inviscid export: 0.1 m lattice, x in [0, 15], |y|,|z| <= 1.4."""
    nodes = reference_nodes
    field = ReferenceField(
        points_m=nodes["points"],
        velocity_m_s=nodes["velocity"],
        pressure_gauge_pa=nodes["pressure"],
        density_kg_m3=nodes["density"],
        name="cd_nozzle_inviscid",
        source="../shared/reference/cd_nozzle_inviscid/fluent_export_3d.csv",
        source_sha256="",
    )
    cv = partition_field(field)
    np.testing.assert_allclose(cv.origin_m, [0.0, -1.5, -1.5])
    assert cv.shape == (30, 6, 6)  # the outlet plane x = 15 makes no 31st slice
    assert cv.n_cv == 741  # DESIGN: "about 740" (paper: 772)
    assert cv.node_count.sum() == field.n_nodes
    # the outlet-plane nodes went into the last slice
    outlet = field.points_m[:, 0] == 15.0
    assert outlet.any()
    assert np.all(cv.index[:, 0] <= 29) and np.any(cv.index[:, 0] == 29)
    # targets are means of the nodes inside: check one CV by brute force
    j = int(np.argmax(np.where(cv.index[:, 0] < 29, cv.node_count, 0)))
    assert cv.node_count[j] == 125  # a full interior cube of the 0.1 m lattice (half-open: 5^3)
    # a full cube of the last slice also holds the 5 x 5 outlet-plane nodes folded into it
    assert cv.node_count[cv.index[:, 0] == 29].max() == 150
    lo = cv.origin_m + cv.index[j] * 0.5
    inside = np.all((field.points_m >= lo) & (field.points_m < lo + 0.5), axis=1)
    assert inside.sum() == cv.node_count[j]
    np.testing.assert_allclose(cv.target_velocity_m_s[j], field.velocity_m_s[inside].mean(axis=0))
    np.testing.assert_allclose(cv.target_pressure_gauge_pa[j], field.pressure_gauge_pa[inside].mean())
    # the throat (x = 6) is fastest
    throat = cv.target_velocity_m_s[:, 0].argmax()
    assert 5.0 <= cv.center_m[throat, 0] <= 7.0


def test_open_volume_fraction_is_the_share_of_a_full_cells_nodes():
    from fisc_ground.fit.partition import open_volume_fraction

    np.testing.assert_allclose(open_volume_fraction(np.array([125, 46, 3]), 125.0), [1.0, 46 / 125, 3 / 125])
    # more nodes than the full-cell estimate (folded outlet plane) is still a full cell
    np.testing.assert_allclose(open_volume_fraction(np.array([150]), 125.0), [1.0])
    with pytest.raises(ValueError, match="nodes_per_full_cell"):
        open_volume_fraction(np.array([3]), 0.0)


def test_full_cell_count_is_the_slice_maximum():
    from fisc_ground.fit.partition import full_cell_node_counts

    got = full_cell_node_counts(np.array([125, 40, 150, 60, 7]), np.array([0, 0, 2, 2, 1]))
    np.testing.assert_array_equal(got, [125, 125, 150, 150, 7])


def test_cv_open_fraction_of_a_round_tunnel_on_a_lattice():
    """A 0.1 m lattice inside a cylinder of radius 0.75 m: the 4 near-axis cubes are full, the
    outer ones partial with their share of the 125 lattice nodes; the outlet slice folds 6
    x-planes into its cells and is still full on the axis."""
    from fisc_ground.fit.partition import cv_open_fraction

    g = np.round(np.arange(-0.7, 0.7001, 0.1), 10)
    x = np.round(np.arange(0.0, 1.0001, 0.1), 10)
    X, Y, Z = np.meshgrid(x, g, g, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    pts = pts[np.hypot(pts[:, 1], pts[:, 2]) <= 0.75]
    n = pts.shape[0]
    cvs = partition(pts, np.tile([1.0, 0, 0], (n, 1)), np.zeros(n), None, cell_size_m=0.5)
    frac = cv_open_fraction(cvs)
    near_axis = np.all(np.abs(cvs.center_m[:, 1:]) < 0.5, axis=1)
    np.testing.assert_allclose(frac[near_axis], 1.0)
    outer = ~near_axis
    assert outer.any() and np.all((frac[outer] > 0) & (frac[outer] < 1))
    first = cvs.index[:, 0] == 0
    np.testing.assert_allclose(frac[first], cvs.node_count[first] / 125.0)
