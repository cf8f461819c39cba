"""Figures a reader trips on (issue 32), tested from the artists' bounding boxes in display coordinates: no legend
over its data, no panel title over the panel above, a key for every line colour, typeset symbols, a caption that
names the line styles drawn, a legend for `simulate`'s trajectories. Synthetic results, the real drawing code."""

from __future__ import annotations

import re
from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402
from matplotlib.colors import to_rgba  # noqa: E402

from pipeline.control import Scene  # noqa: E402
from pipeline.experiments.report import Outputs  # noqa: E402
from pipeline.experiments.results import Results  # noqa: E402

SCENE = Scene()
CTX = SimpleNamespace(scene=SCENE, arena=SCENE.bounds)


@pytest.fixture
def drawn(monkeypatch, tmp_path):
    """The figures a drawing function hands to `Outputs.figure`, drawn (not saved): `(out, {stem: figure})`."""
    figs = {}

    def figure(self, fig, stem, caption):
        fig.canvas.draw()
        figs[stem] = fig
        return []

    monkeypatch.setattr(Outputs, "figure", figure)
    monkeypatch.setattr(Outputs, "table", lambda self, df, stem, caption: [])
    yield Outputs(tmp_path, "x"), figs
    plt.close("all")


def _legends(fig):
    return [lg for lg in [*(ax.get_legend() for ax in fig.axes), *fig.legends] if lg is not None]


def _data_points(ax) -> np.ndarray:
    """Display coordinates of every plotted point (lines, markers, scatter) of an axes, inside its window."""
    pts = [line.get_transform().transform(line.get_xydata()) for line in ax.get_lines() if len(line.get_xydata())]
    pts += [c.get_offset_transform().transform(c.get_offsets()) for c in ax.collections
            if len(c.get_offsets()) and type(c).__name__ == "PathCollection"]
    pts = np.concatenate(pts) if pts else np.zeros((0, 2))
    pts = pts[np.isfinite(pts).all(axis=1)]
    return pts[_inside(ax, pts)]


def _inside(ax, pts):
    box = ax.get_window_extent()
    return (pts[:, 0] >= box.x0) & (pts[:, 0] <= box.x1) & (pts[:, 1] >= box.y0) & (pts[:, 1] <= box.y1)


def _covered(fig) -> list[str]:
    """What each legend covers: data points of any axes, or a bar."""
    r = fig.canvas.get_renderer()
    problems = []
    for lg in _legends(fig):
        box = lg.get_window_extent(r)
        for ax in fig.axes:
            pts = _data_points(ax)
            inside = (pts[:, 0] > box.x0) & (pts[:, 0] < box.x1) & (pts[:, 1] > box.y0) & (pts[:, 1] < box.y1)
            if inside.any():
                problems.append(f"legend {[t.get_text() for t in lg.get_texts()][:3]} covers {inside.sum()} points")
            bars = [p for c in ax.containers for p in getattr(c, "patches", []) if p.get_height() > 0]
            if any(p.get_window_extent(r).overlaps(box) for p in bars):
                problems.append(f"legend {[t.get_text() for t in lg.get_texts()][:3]} covers a bar")
    return problems


def _keyed(ax, legend) -> list[str]:
    """Colours of the axes' data lines and scatter points that no legend entry shows."""
    keys = set()
    for h in legend.legend_handles:
        for get in ("get_color", "get_markerfacecolor", "get_facecolor"):
            if hasattr(h, get):
                c = getattr(h, get)()
                keys.add(tuple(np.round(to_rgba(c if not isinstance(c, np.ndarray) or c.ndim == 1 else c[0]), 3)))
    used = {tuple(np.round(to_rgba(line.get_color()), 3)) for line in ax.get_lines() if len(line.get_xydata()) > 1}
    for c in ax.collections:
        if type(c).__name__ == "PathCollection":
            used |= {tuple(np.round(fc, 3)) for fc in c.get_facecolors()}
    return sorted(str(c) for c in used - keys)


# ------------------------------------------------------------------------------------- legends over data
def _summary(conds=("none", "gaussian"), ctrls=("hybrid", "smooth", "cbf")):
    rows = [{"condition": c, "controller": k, "n": 100, "success_rate": 1.0, "success_lo": 0.96, "success_hi": 1.0,
             "delta_practical": 1.0} for c in conds for k in ctrls]
    return pd.DataFrame(rows)


def test_fig9_s_legend_does_not_cover_its_bars(drawn):
    from pipeline.experiments.paper.figures import draw_monte_carlo

    out, figs = drawn
    draw_monte_carlo(None, CTX, Results({"summary": _summary()}, {}, {}), out)
    assert not _covered(figs["fig9_monte_carlo"])


def test_the_multi_monte_carlo_legend_does_not_cover_its_bars(drawn):
    from pipeline.experiments.multi.figures import draw_multi_monte_carlo

    out, figs = drawn
    t = _summary()
    draw_multi_monte_carlo(None, CTX, Results({"summary": t, "per_scene": t.assign(scene="f0")}, {},
                                              {"scenes": ["f0"]}), out)
    assert not _covered(figs["fig19_multi_monte_carlo"])


@pytest.mark.parametrize("draw, stem", [("draw_camera_attack", "fig14_camera_attack"),
                                        ("draw_worst_cloud", "fig15_worst_cloud")])
def test_the_attack_sweeps_legends_do_not_cover_their_curves(drawn, draw, stem):
    from pipeline.experiments.attacks import figures as attack_figures

    out, figs = drawn
    rows = []
    for b in (0.0, 2.0, 4.0, 8.0):
        for ctrl, gated in (("hybrid", False), ("smooth", False), ("cbf", False), ("hybrid", True)):
            r = {"budget": b, "controller": ctrl, "gated": gated, "n": 50, "induced_norm_near_K": 0.1 * b,
                 "induced_along_start": 0.05 * b, "flag_rate": min(1.0, 0.1 * b)}
            for key, v in (("success", 1.0 if ctrl == "hybrid" else 0.5), ("stalled", 0.0 if ctrl == "hybrid" else 0.5)):
                r.update({f"{key}_rate": v, f"{key}_lo": max(0, v - 0.1), f"{key}_hi": min(1, v + 0.1)})
            rows.append(r)
    res = Results({"summary": pd.DataFrame(rows)}, {}, {})
    scen = SimpleNamespace(id=stem.split("_", 1)[1], attack="worst_cloud", map="occluded")
    ctx = SimpleNamespace(**vars(CTX), cfg=SimpleNamespace(disturbances={"worst_cloud": SimpleNamespace(candidates=4)}))
    getattr(attack_figures, draw)(scen, ctx, res, out)
    assert not _covered(figs[stem])


# --------------------------------------------------------------------------- titles over the panel above
def _titles_clear(fig) -> list[str]:
    r = fig.canvas.get_renderer()
    axes = fig.axes
    bad = []
    for lower in axes:
        title = lower.title.get_window_extent(r)
        for upper in axes:
            if upper is lower or upper.get_position().y0 <= lower.get_position().y0:
                continue
            if title.overlaps(upper.xaxis.get_tightbbox(r)):
                bad.append(f"'{lower.get_title()}' overlaps the x axis of '{upper.get_title()}'")
    return bad


def test_fig2_and_fig3_lower_titles_clear_the_upper_panels(drawn):
    from pipeline.experiments.paper.figures import draw_coverings, draw_sensitive_set

    out, figs = drawn
    x, y = np.linspace(-50, 50, 41), np.linspace(-30, 30, 25)
    X, Y = np.meshgrid(x, y)
    V = np.hypot(X - 40, Y)
    draw_coverings(None, CTX, Results({"coverings": pd.DataFrame()}, {"x": x, "y": y, "V1": V, "V2": V}, {}), out)
    keep = np.ones(len(x) * len(y), bool)
    arrays = {"x": x, "y": y, "keep": keep}
    for ctrl in ("smooth", "hybrid"):
        for case in ("clean", "adversarial eps=0.5"):
            arrays[f"{ctrl}|{case}"] = (np.arange(keep.sum()) % 3).astype(float)
    draw_sensitive_set(None, CTX, Results({"sensitive_set": pd.DataFrame()}, arrays, {"eps": 0.5}), out)
    for stem in ("fig2_sensitive_set", "fig3_coverings"):
        assert not _titles_clear(figs[stem]), stem


# ------------------------------------------------------------------------------ colour keys and mathtext
def test_fig7_left_keys_each_run_and_covers_nothing(drawn, monkeypatch):
    from pipeline.experiments.paper import figures

    monkeypatch.setattr(figures, "_gif", lambda *a, **k: None)
    out, figs = drawn
    t = np.linspace(0, 1, 30)[:, None]
    single_p = np.stack([np.hstack([-12 + 50 * t, 2 + 0 * t]), np.hstack([-37 + 70 * t, -17 + 17 * t])], axis=1)
    lead = single_p[:, :1]
    cols = ["role", "x0", "y0", "success", "outcome", "collision", "time_to_target", "min_clearance", "jumps",
            "final_error"]
    res = Results({"metrics": pd.DataFrame(columns=cols)},
                  {"single_p": single_p, "single_m": single_p + 0.3, "lead_p": lead, "foll_p": lead - 2,
                   "foll_target": lead + 0.2, "foll_t": t[:, 0]}, {"sigma": 0.5, "p_fail": 0.5})
    figures.draw_noise_failure(None, CTX, res, out)
    fig = figs["fig7_robustness_noise_failure"]
    left = fig.axes[0]
    assert left.get_legend() is not None and not _keyed(left, left.get_legend())
    assert not _covered(fig)


def test_the_multi_cells_figure_keys_the_active_obstacle_colours_and_typesets_its_symbols(drawn):
    from pipeline.experiments.multi.figures import draw_multi_cells

    out, figs = drawn
    x, y = np.linspace(-50, 50, 21), np.linspace(-30, 30, 13)
    X, Y = np.meshgrid(x, y)
    t = np.linspace(0, 1, 20)[:, None]
    p = np.stack([np.hstack([-40 + 80 * t, 5 + 0 * t]), np.hstack([-40 + 80 * t, -5 + 0 * t])], axis=1)
    res = Results({"obstacles": pd.DataFrame()},
                  {"x": x, "y": y, "cell": np.zeros_like(X), "band": np.zeros_like(X, bool), "V": np.hypot(X - 40, Y),
                   "p": p, "i": np.zeros(p.shape[:2])}, {"h": 1.0, "summary": "one obstacle"})
    draw_multi_cells(None, CTX, res, out)
    fig = figs["fig17_multi_cells"]
    right = fig.axes[1]
    assert right.get_legend() is not None and not _keyed(right, right.get_legend())
    assert not _covered(fig)
    for text in (a.get_title() for a in fig.axes):
        assert not re.search(r"\b(min_q|V_i|D_i|O_\d|V_\d)", re.sub(r"\$[^$]*\$", "", text)), text
    assert "$" in right.get_title()


def test_fig3_typesets_o_and_v(drawn):
    from pipeline.experiments.paper.figures import draw_coverings

    out, figs = drawn
    x, y = np.linspace(-50, 50, 21), np.linspace(-30, 30, 13)
    V = np.hypot(*np.meshgrid(x - 40, y))
    draw_coverings(None, CTX, Results({"coverings": pd.DataFrame()}, {"x": x, "y": y, "V1": V, "V2": V}, {}), out)
    for ax in figs["fig3_coverings"].axes:
        plain = re.sub(r"\$[^$]*\$", "", ax.get_title())
        assert not re.search(r"[OV]_\d", plain) and re.search(r"\$O_\d\$", ax.get_title()), ax.get_title()


# ----------------------------------------------------------------------------- the coverage caption
@pytest.mark.parametrize("eps_cover", [None, 1.5])
def test_the_coverage_title_names_the_line_styles_it_draws(eps_cover):
    from pipeline.errormap.figures import _coverage_figure

    n = 8
    fields = {"eps_min_none": np.full((n, n), 1.0), "operational": np.ones((n, n), bool)}
    results = {"none": {"coverage": {"eps": [0.5, 1.0, 2.0], "fraction": [0.2, 0.6, 1.0]}, "L": 1.0,
                        "eps_cover": eps_cover}}
    from pipeline.errormap.settings import Coverage, ErrorMapSettings

    settings = ErrorMapSettings(coverage=Coverage(eps_marks=[1.0, 2.0], r_cov=1.0))
    fig = _coverage_figure(fields, results, settings, scene=SCENE, arena=SCENE.bounds,
                           extent=(-50, 50, -30, 30), levels=["none"])
    ax = fig.axes[0]
    vertical = [line for line in ax.get_lines() if len(set(line.get_xdata())) == 1]
    styles = {line.get_linestyle() for line in vertical}
    title = ax.get_title()
    assert ("dotted" in title) == (":" in styles), title
    assert ("grey" in title or "solid" in title) == ("-" in styles), title
    plt.close(fig)


# ------------------------------------------------------------------------------ simulate's trajectories
def test_simulate_s_trajectories_have_a_legend_beside_them():
    from pipeline.viz import trajectory_figure

    t = np.linspace(0, 1, 40)[:, None]
    p = np.stack([np.hstack([-40 + 80 * t, 20 * t]), np.hstack([-40 + 30 * t, -20 * t]),
                  np.hstack([-20 + 60 * t, 10 + 0 * t])], axis=1)
    fig = trajectory_figure(SCENE, p, np.array([True, False, True]), title="t")
    fig.canvas.draw()
    lg = fig.axes[0].get_legend()
    labels = {t.get_text() for t in lg.get_texts()}
    assert {"reached the target", "failed", "start", "target"} <= labels
    assert not _keyed(fig.axes[0], lg) and not _covered(fig)
    plt.close(fig)
