"""The figures of an ε-error map: `|E(p)|` heat maps, the local slope, the coverage sets of Assumption 1, and
the error against the distance to the data (docs/errormap.md)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib import pyplot as plt
from matplotlib.colors import BoundaryNorm, LogNorm, Normalize

from pipeline.control import Scene
from pipeline.errormap.analysis import fmt_eps
from pipeline.viz import draw_scene, save


def _shared_norm(arrays: list[np.ndarray]):
    """One colour scale for all panels: logarithmic when the values span more than 20x (a clean and an
    occluded level side by side), else linear from 0. Returns `(norm, floor)`; plot `max(values, floor)`."""
    vals = np.concatenate([np.asarray(a, dtype=float).ravel() for a in arrays])
    vals = vals[np.isfinite(vals)]
    vmax = float(np.percentile(vals, 99.5)) if vals.size else 1.0
    vmax = vmax if vmax > 0 else 1.0
    pos = vals[vals > 0]
    vmin = max(float(np.percentile(pos, 1)) if pos.size else vmax, vmax * 1e-4)
    if vmax / vmin > 20:
        return LogNorm(vmin=vmin, vmax=vmax), vmin
    return Normalize(vmin=0.0, vmax=vmax), 0.0


def figures(folder: Path, fields: dict, results: dict, scene: Scene, arena, settings, levels) -> list[str]:
    fmts = tuple(settings.formats)
    (x0, x1), (y0, y1) = arena
    view = dict(scene=scene, arena=arena, extent=(x0, x1, y0, y1), levels=levels)
    worst = {lv: np.linalg.norm(fields[f"E_{lv}"], axis=-1).max(axis=0) for lv in levels}  # worst |E| per point
    out = save(_error_map_figure(worst, results, **view), folder / "error_map", fmts)
    if all(f"H_{lv}" in fields for lv in levels):
        out += save(_heading_figure(fields, results, **view), folder / "heading_error_map", fmts)
    out += save(_slope_figure(fields, results, **view), folder / "slope_map", fmts)
    out += save(_coverage_figure(fields, results, settings, **view), folder / "coverage", fmts)
    out += save(_distance_figure(fields, worst, results, levels), folder / "error_vs_distance", fmts)
    return [Path(p).name for p in out]


def _panels(n: int, title: str):
    """One panel per occlusion level, stacked."""
    fig, axes = plt.subplots(n, 1, figsize=(7.5, 3.6 * n), squeeze=False, layout="constrained")
    fig.suptitle(title)
    return fig, axes[:, 0]


def _worst_figure(worst: dict, title: str, label: str, caption, *, scene, arena, extent, levels):
    """One panel per level of a worst-case map `worst[level]` on a shared colour scale; `caption(level)` its title."""
    norm, floor = _shared_norm(list(worst.values()))
    fig, axes = _panels(len(levels), title)
    for ax, lv in zip(axes, levels):
        im = ax.imshow(np.maximum(worst[lv], floor), origin="lower", extent=extent, cmap="magma_r", norm=norm,
                       interpolation="nearest")
        draw_scene(ax, scene, arena)
        ax.set_title(caption(lv), fontsize=9)
        fig.colorbar(im, ax=ax, label=label, extend="max", shrink=0.85)
    return fig


def _error_map_figure(worst: dict, results: dict, **view):
    """The error map: worst |E| per point, one shared colour scale."""
    def caption(lv):
        r = results[lv]
        return f"occlusion {lv}: mean {r['mean']:.2f}, p95 {r['p95']:.2f}, max {r['max']:.2f} (operational set)"
    return _worst_figure(worst, "ε-error map |E(p)| = |l(h(p)) - p|", "|E| (world units)", caption, **view)


def _heading_figure(fields: dict, results: dict, **view):
    """A pose map: the worst heading error per point over the headings drawn, beside |E|."""
    def caption(lv):
        h = results[lv]["heading"]
        return (f"occlusion {lv}: mean {h['mean_deg']:.2f}°, p95 {h['p95_deg']:.2f}°, max {h['max_deg']:.1f}° "
                "(operational set, all headings)")
    worst_h = {lv: np.abs(fields[f"H_{lv}"]).max(axis=0) for lv in view["levels"]}
    return _worst_figure(worst_h, "heading error |θ̂ - θ| of a pose map (worst over the headings drawn)",
                         "|Δθ| (degrees)", caption, **view)


def _slope_figure(fields: dict, results: dict, *, scene, arena, extent, levels):
    """The local slope map (NaN outside the operational set)."""
    slopes = {lv: fields[f"slope_{lv}"] for lv in levels}
    norm, floor = _shared_norm(list(slopes.values()))
    fig, axes = _panels(len(levels), "local slope of E (largest difference quotient to a neighbour)")
    for ax, lv in zip(axes, levels):
        sl = np.where(np.isfinite(slopes[lv]), np.maximum(slopes[lv], floor), np.nan)  # NaN: not operational
        im = ax.imshow(sl, origin="lower", extent=extent, cmap=plt.get_cmap("viridis").with_extremes(bad="0.92"),
                       norm=norm, interpolation="nearest")
        draw_scene(ax, scene, arena)
        ax.set_title(f"occlusion {lv}: L max {results[lv]['L_max']:.3g}, p99 {results[lv]['L_p99']:.3g}",
                     fontsize=9)
        fig.colorbar(im, ax=ax, label="|ΔE| / |Δp|", extend="max", shrink=0.85)
    return fig


def _coverage_figure(fields: dict, results: dict, settings, *, scene, arena, extent, levels):
    """Assumption 1: the coverage curve per level, then its eps_min map with the covered sets of the marks."""
    n = len(levels)
    marks = sorted(settings.coverage.eps_marks or [])
    fig, axes = plt.subplots(n + 1, 1, figsize=(7.5, 3.5 * (n + 1)), squeeze=False, layout="constrained")
    axes = axes[:, 0]
    covered = []
    for lv in levels:
        c = results[lv]["coverage"]
        (line,) = axes[0].plot(c["eps"], c["fraction"], label=f"{lv} (L = {results[lv]['L']:.3g})")
        ec = results[lv]["eps_cover"]
        if ec is not None and math.isfinite(ec):
            axes[0].axvline(ec, ls=":", color=line.get_color())
            covered.append(lv)
    for m in marks:
        axes[0].axvline(m, color="0.6", lw=0.6, ls="-")
    axes[0].set_xlabel("ε")
    axes[0].set_ylabel("covered fraction\nof the operational set")
    axes[0].set_ylim(0, 1.02)
    axes[0].legend(fontsize=8)
    lines = [*(["dotted: the smallest ε whose coverage set holds the operational set"] if covered else []),
             *(["thin grey: the marked ε of the maps below"] if marks else [])]
    axes[0].set_title(f"Assumption 1: p ∈ S(L, ε), r_cov = {settings.coverage.r_cov}"
                      + (f"\n({'; '.join(lines)})" if lines else ""), fontsize=9)
    # nested covered sets: the colour of p is the smallest marked ε whose coverage set contains it
    bounds = [0.0, *marks, np.inf]
    cmap = plt.get_cmap("viridis", len(bounds) - 1).with_extremes(bad="tab:red")
    norm = BoundaryNorm(np.arange(len(bounds)) - 0.5, cmap.N)
    for ax, lv in zip(axes[1:], levels):
        em = fields[f"eps_min_{lv}"]
        band = np.where(np.isfinite(em), np.searchsorted(marks, em, side="left"), np.nan)
        im = ax.imshow(band, origin="lower", extent=extent, cmap=cmap, norm=norm, interpolation="nearest")
        ax.imshow(np.where(fields["operational"], np.nan, 1.0), origin="lower", extent=extent, cmap="Greys",
                  vmin=0, vmax=1.6, alpha=0.75, interpolation="nearest")  # grey veil: not operational
        draw_scene(ax, scene, arena)
        ax.set_title(f"occlusion {lv}: covered sets (red: no sample within r_cov); operational set covered "
                     f"for ε >= {fmt_eps(results[lv]['eps_cover'])}", fontsize=8)
        cb = fig.colorbar(im, ax=ax, ticks=range(len(bounds) - 1), shrink=0.85)
        cb.ax.set_yticklabels([f"ε ≤ {m:g}" for m in marks] + [f"ε > {marks[-1]:g}" if marks else "covered"],
                              fontsize=7)
    return fig


def _distance_figure(fields: dict, worst: dict, results: dict, levels):
    """The error against the distance to the nearest training sample (a fixed subsample of 4000 points)."""
    fig, ax = plt.subplots(figsize=(7, 4), layout="constrained")
    op = fields["operational"].ravel()
    near = fields["nearest"].ravel()[op]
    rng = np.random.default_rng(0)
    for lv in levels:
        w = worst[lv].ravel()[op]
        sub = rng.choice(len(w), size=min(len(w), 4000), replace=False)
        sc = ax.scatter(near[sub], w[sub], s=2, alpha=0.25)
        b = results[lv]["error_vs_distance"]
        mid = (b["lo"] + b["hi"]) / 2
        ax.plot(mid, b["median"], "-o", ms=3, color=sc.get_facecolor()[0][:3], label=f"{lv}: median")
        ax.plot(mid, b["p95"], "--", color=sc.get_facecolor()[0][:3], label=f"{lv}: p95")
    ax.set_xlabel("distance to the nearest training sample")
    ax.set_ylabel("|E(p)|")
    ax.set_title("where the map is trustworthy: error vs distance to the data", fontsize=9)
    ax.legend(fontsize=8)
    return fig
