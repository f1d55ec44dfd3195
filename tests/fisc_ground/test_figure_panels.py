"""Every figure of the main job (``fisc-sim run``) and of a replay (``fisc-ground replay``) says something:
no panel is one flat colour, and no label or title of one panel runs into another panel's.

A panel's data: the arrays of its colour-mapped artists (the CV fields of ``pcolormesh``), or, on a
panel without any, its scatter points and lines.  Colour bars are part of the panel they belong to."""

from __future__ import annotations

import itertools

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from fisc_ground.figures import plots  # noqa: E402
from fisc_ground.figures.field_figures import run_figure_drawings  # noqa: E402
from fisc_ground.monitor.recording import aggregate, read_recording  # noqa: E402
from sim import run as sim_run  # noqa: E402
from sim.run import RunConfig  # noqa: E402


def _is_colorbar(ax) -> bool:
    return hasattr(ax, "_colorbar")


def _mapped_arrays(ax) -> list[np.ndarray]:
    out = []
    for artist in [*ax.collections, *ax.images]:
        arr = artist.get_array()
        if arr is not None:
            a = np.ma.masked_invalid(np.ma.asarray(arr, dtype=float)).compressed()
            out.append(a)
    return out


def _varies(a: np.ndarray) -> bool:
    a = np.asarray(a, dtype=float)
    a = a[np.isfinite(a)]
    return a.size > 0 and float(a.max()) > float(a.min())


def flat_panels(fig: Figure) -> list[str]:
    """Titles of the panels of ``fig`` that show one flat colour (or nothing)."""
    flat = []
    for ax in fig.axes:
        if _is_colorbar(ax) or not ax.axison:
            continue
        mapped = _mapped_arrays(ax)
        if mapped:
            ok = all(_varies(a) for a in mapped)
        else:
            points = [np.asarray(c.get_offsets(), dtype=float) for c in ax.collections]
            lines = [np.asarray(line.get_ydata(), dtype=float) for line in ax.get_lines()]
            ok = any(p.shape[0] > 1 and _varies(p[:, 1]) for p in points) or any(_varies(y) for y in lines)
        if not ok:
            flat.append(ax.get_title() or "<untitled panel>")
    return flat


def _panel_of(fig: Figure, ax):
    """A colour bar belongs to the axes it was drawn for."""
    if _is_colorbar(ax):
        for other in fig.axes:
            if not _is_colorbar(other) and any(getattr(c, "colorbar", None) is ax._colorbar
                                               for c in [*other.collections, *other.images]):
                return other
    return ax


def overlapping_texts(fig: Figure) -> list[tuple[str, str]]:
    """Pairs (text, text) of labels / titles of different panels (and the figure's title) whose
    rendered bounding boxes overlap."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    texts = []  # (panel, text artist)
    for ax in fig.axes:
        if not ax.axison:
            continue
        panel = _panel_of(fig, ax)
        for t in (ax.title, ax._left_title, ax._right_title, ax.xaxis.label, ax.yaxis.label):
            texts.append((panel, t))
    if fig._suptitle is not None:
        texts.append((None, fig._suptitle))
    boxes = [(p, t, t.get_window_extent(renderer)) for p, t in texts if t.get_visible() and t.get_text()]
    bad = []
    for (p1, t1, b1), (p2, t2, b2) in itertools.combinations(boxes, 2):
        if p1 is not p2 and b1.overlaps(b2):
            bad.append((t1.get_text(), t2.get_text()))
    return bad


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The main job (default map, paper preset beside it; short), its paper companion alone (a
    schema-1 run) and a replay of the main job's flight log."""
    tmp = tmp_path_factory.mktemp("figs")
    r = sim_run.run(RunConfig(duration_s=10.0, average_window_s=5.0, figures=False, out_dir=str(tmp / "run"),
                              mcap=str(tmp / "run.mcap")))
    replayed = aggregate(read_recording(tmp / "run.mcap")).field_run(min_samples=1)
    return {"main job": r.field_run, "paper preset": r.paper.field_run, "replay": replayed}


@pytest.mark.parametrize("which", ["main job", "paper preset", "replay"])
def test_every_panel_of_every_figure_varies_and_no_label_runs_into_another_panel(runs, which):
    drawings = run_figure_drawings(runs[which])
    assert {"velocity_cfd_fit_swarm", "pressure_cfd_fit_swarm", "density_cfd_fit_swarm",
            "density_velocity_swarm", "centreline"} <= set(drawings)
    for name, draw in drawings.items():
        fig = draw()
        try:
            assert not flat_panels(fig), f"{which} {name}: flat panels {flat_panels(fig)}"
            assert not overlapping_texts(fig), f"{which} {name}: overlapping {overlapping_texts(fig)}"
        finally:
            plt.close(fig)


def test_the_density_figure_shows_what_the_map_asks_for(runs):
    """Schema 2: panel (b) is the map's designed density rho_d.  Schema 1 with one N* everywhere: no
    panel (b), and the figure's title says why."""
    main = run_figure_drawings(runs["main job"])["density_cfd_fit_swarm"]()
    paper = run_figure_drawings(runs["paper preset"])["density_cfd_fit_swarm"]()
    try:
        panels = [ax for ax in main.axes if not _is_colorbar(ax)]
        assert panels[1].get_title().startswith("(b) designed density rho_d")
        mesh = next(c for c in panels[1].collections if c.get_array() is not None)
        cmap = runs["main job"].cmap
        rho_d = np.asarray(cmap["cv_design_density"], dtype=float)
        _, _, expected = plots.xz_slice(cmap["cv_center_m"], (rho_d - rho_d.min()) / np.ptp(rho_d),
                                        cmap.cell_size_m)
        np.testing.assert_allclose(np.ma.filled(np.ma.asarray(mesh.get_array(), dtype=float), np.nan),
                                   expected, equal_nan=True)
        paper_titles = [ax.get_title() for ax in paper.axes if not _is_colorbar(ax)]
        assert not any(t.startswith("(b)") for t in paper_titles) and len(paper_titles) == 2
        assert "no panel (b)" in paper._suptitle.get_text()
    finally:
        plt.close(main)
        plt.close(paper)


# --- the checks themselves, at their boundaries -------------------------------------------------------


def _panel(values, title="p"):
    fig, ax = plt.subplots(layout="constrained")
    ax.pcolormesh(np.asarray(values, dtype=float).reshape(1, -1))
    ax.set_title(title)
    return fig


def test_flat_panel_check_fails_a_constant_field_and_passes_a_varying_one():
    for values, flat in (([1.0, 1.0, 1.0], True), ([1.0, 1.0, 1.0 + 1e-9], False), ([np.nan, 2.0, 2.0], True),
                         ([np.nan, np.nan], True), ([0.0, 1.0], False)):
        fig = _panel(values)
        try:
            assert (flat_panels(fig) == ["p"]) is flat, values
        finally:
            plt.close(fig)
    fig, ax = plt.subplots()
    ax.plot([0, 1], [2, 2])
    ax.set_title("line")
    assert flat_panels(fig) == ["line"]
    ax.plot([0, 1], [2, 3])
    assert flat_panels(fig) == []
    plt.close(fig)


def test_overlap_check_fails_a_label_under_the_next_title_and_passes_constrained_layout():
    """Three stacked tunnel panels (15 m x 3 m) as plot_xz_comparison drew them before its constrained
    layout: each x label ran into the next panel's title."""
    c = np.array([[x, 0.25, z] for x in np.arange(0.25, 15, 0.5) for z in np.arange(-1.25, 1.3, 0.5)])
    fields = {"(a) one": c[:, 0], "(b) two": c[:, 2], "(c) three": c[:, 0] * c[:, 2]}
    good = plots.xz_comparison_figure(c, fields, 0.5, "title")
    try:
        assert overlapping_texts(good) == []
    finally:
        plt.close(good)
    bad, axes = plt.subplots(3, 1, figsize=(10, 2.6 * 3))
    for ax, (name, values) in zip(axes, fields.items()):
        plots.xz_field_panel(ax, c, values, 0.5, name)
    try:
        assert sorted(overlapping_texts(bad)) == [("x [m]", "(b) two"), ("x [m]", "(c) three")]
    finally:
        plt.close(bad)
