"""Control-volume lookup and velocity commands from a command map (vectorised, numpy only).

The CVs sit on a regular grid, so the nearest CV centre (the paper's CV-assignment equation,
``argmin_j ||x_i - x_j||``) of a point inside an occupied grid cell is that cell's CV: the
lookup is O(1) per agent through the map's dense ``grid_cv`` table, with no search over CVs.
Points in cells without a CV are *outside the map* (id -1); what happens to them is a policy
of the caller (geofence), never an arbitrary far CV.  ``nearest_cv_within`` finds the nearest
existing CV in a bounded neighbourhood for the "return to the map" policy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fisc_agent.mapfile import CommandMap

COMMAND_MODES = ("mean", "slot", "interpolated")


def slot_hash(agent_id: np.ndarray | int, cv_id: np.ndarray | int) -> np.ndarray:
    """h(agent_id, j): a fixed 32-bit integer mix, identical on every agent and the simulator.

    Agent i in CV j flies fitted vector ``h(i, j) mod N*_j`` (DESIGN.md section 3, ``slot``).
    """
    a = np.asarray(agent_id, dtype=np.uint64) & np.uint64(0xFFFFFFFF)
    j = np.asarray(cv_id, dtype=np.uint64) & np.uint64(0xFFFFFFFF)
    h = (a * np.uint64(0x9E3779B1)) ^ (j * np.uint64(0x85EBCA77) + np.uint64(0x27D4EB2F))
    h &= np.uint64(0xFFFFFFFF)
    h ^= h >> np.uint64(15)
    h = (h * np.uint64(0x2C1B3C6D)) & np.uint64(0xFFFFFFFF)
    h ^= h >> np.uint64(12)
    return h


def slot_index(agent_id: np.ndarray | int, cv_id: np.ndarray | int, n_star: np.ndarray | int) -> np.ndarray:
    """k = h(agent_id, j) mod N*_j as int64: the fitted vector agent ``agent_id`` flies in CV ``cv_id``."""
    return (slot_hash(agent_id, cv_id) % np.asarray(n_star, dtype=np.uint64)).astype(np.int64)


def lookahead_point(points_m: np.ndarray, velocity_m_s: np.ndarray, lead_s: float) -> np.ndarray:
    """Point ``x + u t_lead`` whose command an agent flies to compensate its velocity lag.

    A velocity-controlled multirotor responds to a command with a lag of roughly its time
    constant tau, so an agent that looks up the command at its own position flies the command
    of the point about ``u tau`` behind it.  Looking the command up ``t_lead ~ tau`` ahead
    along the current velocity cancels that to first order.  ``points_m`` and ``velocity_m_s``
    are (m, 3) in the same frame; ``lead_s`` >= 0 (0 returns a copy of the points).
    """
    if not (lead_s >= 0 and np.isfinite(lead_s)):
        raise ValueError(f"lead_s must be finite and >= 0, got {lead_s!r}")
    return np.asarray(points_m, dtype=float) + float(lead_s) * np.asarray(velocity_m_s, dtype=float)


@dataclass(frozen=True)
class CommandField:
    """A map's commands prepared for fast lookup (all arrays in the map/reference frame)."""

    origin_m: np.ndarray
    """(3,) lower corner of grid cell (0, 0, 0) [m]."""
    cell_size_m: float
    """CV edge length l [m]."""
    grid_cv: np.ndarray
    """(nx, ny, nz) CV id per grid cell, -1 where there is none."""
    centers_m: np.ndarray
    """(n_cv, 3) CV centres [m]."""
    mean_cmd_m_s: np.ndarray
    """(n_cv, 3) scaled mean command S * v_{s,d,j} [m/s]."""
    slot_cmd_m_s: np.ndarray
    """(n_cv, n_max, 3) scaled fitted vectors (NaN beyond N*) [m/s]."""
    n_star: np.ndarray
    """(n_cv,) fitted agent count N*_j."""

    @classmethod
    def from_map(cls, cmap: CommandMap, scale: float | None = None) -> "CommandField":
        s = cmap.scale if scale is None else float(scale)
        return cls(
            origin_m=cmap.origin_m,
            cell_size_m=cmap.cell_size_m,
            grid_cv=np.asarray(cmap["grid_cv"]),
            centers_m=np.asarray(cmap["cv_center_m"]),
            mean_cmd_m_s=s * np.asarray(cmap["fit_mean_velocity_m_s"]),
            slot_cmd_m_s=s * np.asarray(cmap["fit_velocity_m_s"]),
            n_star=np.asarray(cmap["n_star"]),
        )

    @property
    def n_cv(self) -> int:
        return int(self.centers_m.shape[0])

    def cell_of(self, points_m: np.ndarray) -> np.ndarray:
        """(m, 3) integer grid cell of each point (half-open cells; may be out of range)."""
        return np.floor((np.asarray(points_m, dtype=float) - self.origin_m) / self.cell_size_m).astype(np.int64)

    def cv_of(self, points_m: np.ndarray) -> np.ndarray:
        """(m,) CV id of each point, -1 outside the map's CVs."""
        cells = self.cell_of(np.atleast_2d(points_m))
        shape = np.asarray(self.grid_cv.shape)
        inside = np.all((cells >= 0) & (cells < shape), axis=1)
        ids = np.full(cells.shape[0], -1, dtype=np.int64)
        c = cells[inside]
        ids[inside] = self.grid_cv[c[:, 0], c[:, 1], c[:, 2]]
        return ids

    def nearest_cv_within(self, points_m: np.ndarray, radius_cells: int = 2) -> np.ndarray:
        """(m,) nearest existing CV (by centre distance) within ``radius_cells`` grid cells, else -1."""
        pts = np.atleast_2d(np.asarray(points_m, dtype=float))
        cells = self.cell_of(pts)
        r = np.arange(-radius_cells, radius_cells + 1)
        offs = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
        cand = cells[:, None, :] + offs[None, :, :]  # (m, k, 3)
        shape = np.asarray(self.grid_cv.shape)
        ok = np.all((cand >= 0) & (cand < shape), axis=2)
        ids = np.full(ok.shape, -1, dtype=np.int64)
        cc = cand[ok]
        ids[ok] = self.grid_cv[cc[:, 0], cc[:, 1], cc[:, 2]]
        d2 = np.where(ids >= 0, np.sum((self.centers_m[np.maximum(ids, 0)] - pts[:, None, :]) ** 2, axis=2), np.inf)
        best = np.argmin(d2, axis=1)
        out = ids[np.arange(len(pts)), best]
        out[~np.isfinite(d2[np.arange(len(pts)), best])] = -1
        return out

    def command(self, points_m: np.ndarray, agent_ids: np.ndarray, mode: str = "mean",
                cv_ids: np.ndarray | None = None) -> np.ndarray:
        """(m, 3) commanded velocity [m/s] in the map frame; NaN rows for points outside the map."""
        pts = np.atleast_2d(np.asarray(points_m, dtype=float))
        cv = self.cv_of(pts) if cv_ids is None else np.asarray(cv_ids)
        out = np.full((pts.shape[0], 3), np.nan)
        ok = cv >= 0
        if mode == "mean":
            out[ok] = self.mean_cmd_m_s[cv[ok]]
        elif mode == "slot":
            j = cv[ok]
            ids = np.asarray(agent_ids)[ok] if np.ndim(agent_ids) else agent_ids
            out[ok] = self.slot_cmd_m_s[j, slot_index(ids, j, self.n_star[j])]
        elif mode == "interpolated":
            out[ok] = self._interpolate(pts[ok], cv[ok])
        else:
            raise ValueError(f"unknown command mode {mode!r}; choose one of {', '.join(COMMAND_MODES)}")
        return out

    def _interpolate(self, pts: np.ndarray, cv: np.ndarray) -> np.ndarray:
        """Trilinear interpolation of the mean command between CV centres.

        Corners without a CV are left out and the remaining weights renormalised; a point
        with no CV among its 8 corners keeps its own CV's command.
        """
        f = (pts - self.origin_m) / self.cell_size_m - 0.5
        i0 = np.floor(f).astype(np.int64)
        t = f - i0
        acc = np.zeros((pts.shape[0], 3))
        wsum = np.zeros(pts.shape[0])
        shape = np.asarray(self.grid_cv.shape)
        for corner in range(8):
            d = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
            c = i0 + d
            w = np.prod(np.where(d == 1, t, 1.0 - t), axis=1)
            inside = np.all((c >= 0) & (c < shape), axis=1)
            ids = np.full(len(pts), -1, dtype=np.int64)
            ids[inside] = self.grid_cv[c[inside, 0], c[inside, 1], c[inside, 2]]
            w = np.where(ids >= 0, w, 0.0)
            acc += w[:, None] * self.mean_cmd_m_s[np.maximum(ids, 0)]
            wsum += w
        out = self.mean_cmd_m_s[cv].copy()
        good = wsum > 1e-12
        out[good] = acc[good] / wsum[good, None]
        return out
