"""The monitor's terminal dashboard (rich): fleet table, alarms, density and pressure heat maps."""

from __future__ import annotations

from typing import Any

import numpy as np

from fisc_agent.map.codec import CommandMap
from fisc_ground.monitor.aggregator import FleetView
from fisc_ground.fields.swarm_fields import SwarmFields

_PALETTE = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], dtype=float)


def _colour(v: float) -> str:
    x = min(max(v, 0.0), 1.0) * (len(_PALETTE) - 1)
    i = min(int(x), len(_PALETTE) - 2)
    r, g, b = _PALETTE[i] + (x - i) * (_PALETTE[i + 1] - _PALETTE[i])
    return f"on rgb({int(r)},{int(g)},{int(b)})"


def heatmap_text(cmap: CommandMap, values: np.ndarray, max_cols: int = 60) -> Any:
    """A rich Text heat map of per-CV values on the XZ plane (layers nearest y = 0, z up)."""
    from rich.text import Text

    from fisc_ground.figures.plots import xz_slice

    _, _, grid = xz_slice(np.asarray(cmap["cv_center_m"]), np.asarray(values, dtype=float), cmap.cell_size_m)
    step = max(1, -(-grid.shape[1] // max_cols))
    if step > 1:
        cols = -(-grid.shape[1] // step)
        pad = np.full((grid.shape[0], cols * step - grid.shape[1]), np.nan)
        grid = np.nanmean(np.concatenate([grid, pad], axis=1).reshape(grid.shape[0], cols, step), axis=2)
    finite = grid[np.isfinite(grid)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    text = Text()
    for row in grid[::-1]:
        for v in row:
            text.append("  ", style=_colour((v - lo) / (hi - lo) if hi > lo else 0.5) if np.isfinite(v) else "")
        text.append("\n")
    text.append(f"min {lo:.3g}  max {hi:.3g}" if finite.size else "no samples yet")
    return text


def separation_text(view: FleetView) -> str:
    """``now 0.41 m (agents 3, 5); since start 0.08 m, 2 near-misses < d_min 0.92 m``."""
    now = "-" if view.closest_m is None else f"{view.closest_m:.2f} m (agents {view.closest_ids[0]}, {view.closest_ids[1]})"
    a = view.approach or {}
    best = a.get("closest_approach_m")
    since = "" if best is None else f"; since start {best:.2f} m, {a.get('near_misses', 0)} near-misses"
    return f"now {now}{since} < d_min {view.d_min_m:.2f} m" if since else f"now {now}; d_min {view.d_min_m:.2f} m"


def render(view: FleetView, fields: SwarmFields | None, cmap: CommandMap | None, dropped: int, title: str,
           worker_errors: int = 0, last_error: str = "") -> Any:
    """The dashboard as one rich renderable."""
    from rich.console import Group
    from rich.panel import Panel
    from rich.table import Table

    table = Table(title="agents by state", expand=False)
    table.add_column("state")
    table.add_column("agents", justify="right")
    for state, n in sorted(view.by_state.items()):
        table.add_row(state, str(n))
    table.add_row("stale", str(len(view.stale)), style="red" if view.stale else "")
    info = Table.grid(padding=(0, 2))
    info.add_row("agents heard", str(view.n_agents))
    info.add_row("map", f"{cmap.sha256[:12]} v{cmap.map_version} ({cmap.n_cv} CVs)" if cmap else "none yet")
    info.add_row("authority", ", ".join(f"{k}: {v}" for k, v in sorted((view.by_authority or {}).items())) or "-",
                 style="bold red" if (view.by_authority or {}).get("hands-off") else "")
    info.add_row("map versions flown", ", ".join(f"v{k}: {v}" for k, v in sorted(view.map_versions.items())) or "-")
    info.add_row("messages", f"{view.messages}  (bad {view.bad_messages}, dropped {dropped}, "
                             f"off roster {view.off_roster}, over agent cap {view.over_cap})")
    if worker_errors:
        info.add_row("worker errors", f"{worker_errors} batches failed; last: {last_error}", style="bold red")
    info.add_row("field samples", str(view.time_samples))
    info.add_row("closest approach", separation_text(view),
                 style="bold red" if view.closest_m is not None and view.closest_m < view.d_min_m else "")
    for line in view.statistics:
        info.add_row("", line)
    parts: list[Any] = [Panel(info, title=title), table]
    alarms = "\n".join(view.alarms) if view.alarms else "none"
    parts.append(Panel(alarms, title="alarms", style="bold red" if view.alarms else "green"))
    if cmap is not None and fields is not None and view.time_samples:
        parts.append(Panel(heatmap_text(cmap, np.where(fields.samples > 0, fields.rho_s_kg_m3, np.nan)),
                           title="swarm density rho_s [kg/m^3], XZ plane"))
        parts.append(Panel(heatmap_text(cmap, np.where(fields.samples > 0, fields.p_dispersion_pa, np.nan)),
                           title="swarm pressure [Pa], XZ plane"))
    return Group(*parts)
