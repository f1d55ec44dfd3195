"""Cubic control-volume (CV) partition of a reference flow field and the per-CV target means.

Implements the paper's "Spatial Partitioning" step with the grid rules of DESIGN.md section 2:

* cubes of edge ``l`` (default 0.5 m) on a grid aligned with the data's extent: x starts at the
  inlet plane (the data's x_min); in y and z the grid is snapped so that the tunnel axis
  (y = 0, z = 0) lies on cell faces (origin = floor(min / l) * l, which for data symmetric about
  the axis is -ceil(max|y| / l) * l);
* half-open cells ``[lo, lo + l)``, so lattice nodes lying on a face fall deterministically into
  the upper cell;
* no cell beyond the data: nodes exactly on the data's upper extent (the outlet plane
  x = x_max, and likewise y_max, z_max) fold into the last slice instead of creating a slice of
  their own;
* a CV exists where at least ``min_nodes`` nodes fall inside; its targets are the means of those
  nodes; CVs are numbered lexicographically in (i, j, k);
* with ``staircase_contrast`` given, only the cubes of each axial slice that the designed staircase
  keeps (``fisc_ground.fit.staircase``: a per-slice minimum node count) become CVs.

Coordinates within ``FACE_TOL`` cell sizes of a face are treated as lying on it, so that round-off
in exported coordinates (``4.999999e-01``) does not move a lattice node into the wrong cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fisc_ground.reference.field import ReferenceField
from fisc_ground.fit.staircase import designed_staircase, slice_pattern

#: Relative tolerance (in cell sizes) within which a coordinate counts as lying on a cell face.
FACE_TOL = 1e-6


@dataclass(frozen=True)
class ControlVolumes:
    """The cubic CV partition of a reference field and the per-CV CFD targets (reference frame)."""

    origin_m: np.ndarray
    """(3,) float64 lower corner of cell (0, 0, 0) [m]: (x_min, snapped y_min, snapped z_min)."""
    cell_size_m: float
    """Edge length l of the cubic cells [m]."""
    shape: tuple[int, int, int]
    """Grid shape (nx, ny, nz) in cells."""
    index: np.ndarray
    """(n_cv, 3) int32 grid indices (i, j, k) of each CV, lexicographically sorted."""
    center_m: np.ndarray
    """(n_cv, 3) float64 CV centres origin + (index + 0.5) l [m]."""
    node_count: np.ndarray
    """(n_cv,) int32 number of reference nodes inside each CV."""
    target_velocity_m_s: np.ndarray
    """(n_cv, 3) float64 mean CFD velocity of the nodes in each CV [m/s]."""
    target_pressure_gauge_pa: np.ndarray
    """(n_cv,) float64 mean CFD gauge static pressure of the nodes in each CV [Pa]."""
    target_density_kg_m3: np.ndarray
    """(n_cv,) float64 mean CFD density of the nodes in each CV [kg/m^3]; NaN if unknown."""
    grid_cv: np.ndarray
    """(nx, ny, nz) int32 CV id of every grid cell, -1 where no CV exists."""
    staircase_contrast: float | None = None
    """Contrast of the designed staircase that chose the CVs (``fisc_ground.fit.staircase``); None: every cube
    with ``min_nodes`` is a CV (none asked for, or the reference has no slice pattern to follow)."""

    @property
    def n_cv(self) -> int:
        """Number of control volumes."""
        return int(self.index.shape[0])

    @property
    def cell_volume_m3(self) -> float:
        """Volume l^3 of one CV [m^3]."""
        return float(self.cell_size_m) ** 3


def grid_origin_and_shape(
    points_m: np.ndarray, cell_size_m: float
) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Grid origin and shape for data points under the rules of DESIGN.md section 2.

    x origin is the data's x_min (the inlet plane); y/z origins are ``floor(min / l) * l`` so the
    axis y = z = 0 lies on cell faces. The shape is the smallest number of cells that covers the
    data, counting nodes on the upper extent as folded into the last cell.
    """
    pts = np.asarray(points_m, dtype=np.float64)
    l = float(cell_size_m)
    lo = pts.min(axis=0)
    hi = pts.max(axis=0)
    origin = np.empty(3)
    origin[0] = lo[0]
    origin[1:] = np.floor(lo[1:] / l + FACE_TOL) * l
    n = np.ceil((hi - origin) / l - FACE_TOL).astype(np.int64)
    n = np.maximum(n, 1)
    return origin, (int(n[0]), int(n[1]), int(n[2]))


def cell_of(
    points_m: np.ndarray,
    origin_m: np.ndarray,
    cell_size_m: float,
    shape: tuple[int, int, int],
) -> np.ndarray:
    """Grid cell (i, j, k) of each point: ``floor((p - origin) / l)`` with half-open cells.

    Points on the grid's upper boundary face (within ``FACE_TOL`` cells) fold into the last
    cell, as the partition does for nodes on the data's upper extent. Other points outside the
    grid get out-of-range indices (negative or >= shape); callers decide what that means.

    Returns an (m, 3) int64 array.
    """
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    l = float(cell_size_m)
    rel = (pts - np.asarray(origin_m, dtype=np.float64)) / l
    idx = np.floor(rel + FACE_TOL).astype(np.int64)
    shp = np.asarray(shape, dtype=np.int64)
    on_upper_face = (idx == shp) & (rel <= shp + FACE_TOL)
    return np.where(on_upper_face, shp - 1, idx)


def partition(
    points_m: np.ndarray,
    velocity_m_s: np.ndarray,
    pressure_gauge_pa: np.ndarray,
    density_kg_m3: np.ndarray | None,
    cell_size_m: float = 0.5,
    min_nodes: int = 1,
    staircase_contrast: float | None = None,
) -> ControlVolumes:
    """Partition nodes into cubic CVs and average the CFD fields per CV (paper: Spatial Partitioning).

    Target per CV j: ``v_target,j = mean(v_CFD(x))`` and ``P_target,j = mean(P_CFD(x))`` over the
    nodes x inside the CV (and the same for density when given). Vectorised with
    ``np.bincount``; CVs come out in lexicographic (i, j, k) order.

    ``staircase_contrast``: None keeps every cube with ``min_nodes`` (DESIGN.md section 2); a value C
    keeps per slice the cubes ``fisc_ground.fit.staircase.designed_staircase`` chooses for contrast C,
    following the slice pattern of the density (of the pressure where the density is unknown or the
    same in every slice; every cube when both are).

    Raises ValueError on empty or non-finite input, bad shapes, ``cell_size_m <= 0`` or
    ``min_nodes < 1``, and for a staircase that cannot be designed (``designed_staircase``).
    """
    pts = np.asarray(points_m, dtype=np.float64)
    vel = np.asarray(velocity_m_s, dtype=np.float64)
    prs = np.asarray(pressure_gauge_pa, dtype=np.float64)
    rho = None if density_kg_m3 is None else np.asarray(density_kg_m3, dtype=np.float64)
    if not (np.isfinite(cell_size_m) and cell_size_m > 0):
        raise ValueError(f"cell_size_m must be a positive finite number, got {cell_size_m!r}")
    if int(min_nodes) < 1:
        raise ValueError(f"min_nodes must be >= 1, got {min_nodes!r}")
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise ValueError(f"points_m must be a non-empty (n, 3) array, got shape {pts.shape}")
    n = pts.shape[0]
    if vel.shape != (n, 3):
        raise ValueError(f"velocity_m_s must have shape ({n}, 3), got {vel.shape}")
    if prs.shape != (n,):
        raise ValueError(f"pressure_gauge_pa must have shape ({n},), got {prs.shape}")
    if rho is not None and rho.shape != (n,):
        raise ValueError(f"density_kg_m3 must have shape ({n},), got {rho.shape}")
    for name, arr in (("points_m", pts), ("velocity_m_s", vel), ("pressure_gauge_pa", prs),
                      ("density_kg_m3", rho)):
        if arr is not None and not np.all(np.isfinite(arr)):
            bad = int(np.flatnonzero(~np.all(np.isfinite(arr.reshape(n, -1)), axis=1))[0])
            raise ValueError(f"{name} has a non-finite value at node {bad}")

    l = float(cell_size_m)
    origin, shape = grid_origin_and_shape(pts, l)
    ijk = cell_of(pts, origin, l, shape)
    nx, ny, nz = shape
    flat = (ijk[:, 0] * ny + ijk[:, 1]) * nz + ijk[:, 2]
    n_cells = nx * ny * nz

    counts = np.bincount(flat, minlength=n_cells)
    keep_cell = counts >= int(min_nodes)
    pattern = None
    if staircase_contrast is not None:
        # the density's slice pattern, the pressure's where the density is unknown or uniform
        for f in (rho, prs):
            if f is not None and pattern is None:
                pattern = slice_pattern(np.bincount(flat, weights=f, minlength=n_cells).reshape(nx, -1),
                                        counts.reshape(nx, -1))
    if pattern is not None:
        covered = np.where(keep_cell, counts, 0).reshape(nx, -1)
        u_axial = np.bincount(flat, weights=vel[:, 0], minlength=n_cells).reshape(nx, -1) / np.maximum(covered, 1)
        keep_cell &= designed_staircase(covered, u_axial, pattern, staircase_contrast).reshape(-1)
    occupied = np.flatnonzero(keep_cell)  # sorted -> lexicographic (i, j, k)
    n_cv = occupied.size
    grid_cv = np.full(n_cells, -1, dtype=np.int32)
    grid_cv[occupied] = np.arange(n_cv, dtype=np.int32)

    cv_of_node = grid_cv[flat]
    keep = cv_of_node >= 0
    cv_k = cv_of_node[keep]
    cnt = counts[occupied].astype(np.float64)

    def cv_mean(values: np.ndarray) -> np.ndarray:
        return np.bincount(cv_k, weights=values[keep], minlength=n_cv) / cnt

    target_v = np.stack([cv_mean(vel[:, c]) for c in range(3)], axis=1)
    target_p = cv_mean(prs)
    target_rho = cv_mean(rho) if rho is not None else np.full(n_cv, np.nan)

    index = np.stack(np.unravel_index(occupied, shape), axis=1).astype(np.int32)
    center = origin + (index + 0.5) * l
    return ControlVolumes(
        origin_m=origin,
        cell_size_m=l,
        shape=shape,
        index=index,
        center_m=center,
        node_count=counts[occupied].astype(np.int32),
        target_velocity_m_s=target_v,
        target_pressure_gauge_pa=target_p,
        target_density_kg_m3=target_rho,
        grid_cv=grid_cv.reshape(shape),
        staircase_contrast=None if pattern is None else float(staircase_contrast),
    )


def partition_field(
    field: ReferenceField, cell_size_m: float = 0.5, min_nodes: int = 1, staircase_contrast: float | None = None
) -> ControlVolumes:
    """``partition`` applied to a ReferenceField's nodes, velocity, gauge pressure and density."""
    return partition(
        field.points_m,
        field.velocity_m_s,
        field.pressure_gauge_pa,
        field.density_kg_m3,
        cell_size_m=cell_size_m,
        min_nodes=min_nodes,
        staircase_contrast=staircase_contrast,
    )


def full_cell_node_counts(node_count: np.ndarray, slice_index: np.ndarray) -> np.ndarray:
    """Estimated node count of a *full* (entirely open) cell, per CV: the largest node count
    among the CVs of the same axial slice.

    On a regular lattice of spacing h every full cell holds (l/h)^3 nodes (125 for the shipped
    0.1 m references with l = 0.5 m; the folded outlet slice holds 6/5 of that), and the
    near-axis CVs of a tunnel slice are full, so the slice maximum recovers that number
    whatever the axial resolution of the slice.  ``node_count`` and ``slice_index`` (the grid
    x index) are (n_cv,) arrays.  Returns (n_cv,) float64.
    """
    counts = np.asarray(node_count, dtype=np.float64)
    sl = np.asarray(slice_index, dtype=np.int64)
    if counts.shape != sl.shape or counts.ndim != 1:
        raise ValueError(f"node_count and slice_index must be equal (n,) arrays, got {counts.shape} and {sl.shape}")
    if counts.size == 0:
        return counts.copy()
    if sl.min() < 0:
        raise ValueError("slice_index must be >= 0")
    top = np.zeros(int(sl.max()) + 1)
    np.maximum.at(top, sl, counts)
    return top[sl]


def open_volume_fraction(node_count: np.ndarray, nodes_per_full_cell: np.ndarray | float) -> np.ndarray:
    """Open-volume fraction A_j dx_j / l^3 of each CV (the paper's effective cross-section A_j of
    eq. swarm_density), estimated as node_count / nodes_per_full_cell, clipped to (0, 1].

    The reference nodes sample only the flow domain, so on a uniform lattice the share of a full
    cell's nodes that a CV holds is the share of its volume inside the tunnel (a staircase wall CV
    with 46 of 125 nodes is 37 % open).  ``nodes_per_full_cell``: scalar (e.g. 125 = (l/h)^3 for
    lattice spacing h) or per-CV (``full_cell_node_counts``).  Returns (n_cv,) float64.
    """
    counts = np.asarray(node_count, dtype=np.float64)
    full = np.broadcast_to(np.asarray(nodes_per_full_cell, dtype=np.float64), counts.shape)
    if np.any(~(full > 0.0)):
        raise ValueError("nodes_per_full_cell must be > 0")
    if np.any(counts < 0):
        raise ValueError("node_count must be >= 0")
    frac = counts / full
    return np.clip(frac, np.minimum(1.0, 1.0 / full), 1.0)


def cv_open_fraction(cvs: ControlVolumes) -> np.ndarray:
    """(n_cv,) open-volume fraction of every CV of a partition (``open_volume_fraction`` with the
    per-slice full-cell estimate ``full_cell_node_counts``).  Stored in maps as ``cv_open_fraction``."""
    return open_volume_fraction(cvs.node_count, full_cell_node_counts(cvs.node_count, cvs.index[:, 0]))
