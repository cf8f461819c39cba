"""The bracket over the arena (docs/bracket.md): per controller, the start cells coloured by `ε_lo` (certified;
hatched where the certificate holds with the error map's `ε̄`: Theorem 1 for the learned map) and by `ε_hi`
(falsified; hatched where a run within the map's `ε̄` fails), with the obstacle, the diamond, `K` and the counterexamples of smallest `ε_hi`."""

from __future__ import annotations

import numpy as np
from matplotlib import pyplot as plt
from matplotlib.patches import Circle, Polygon, Rectangle

from pipeline.control import diamond_vertices


def _scene(ax, scene):
    (x0, x1), (y0, y1) = scene.bounds
    for i, cov in enumerate(scene.coverings):  # each obstacle, its diamond and K (its axis behind it, to the arena)
        ax.add_patch(Polygon(diamond_vertices(cov), closed=True, fill=False, ec="k", lw=0.8))
        ax.add_patch(Circle(cov.p_0, cov.obstacle_radius, color="0.3"))
        back = -cov.e_a
        steps = [(lim - p) / d for p, d, lims in zip(cov.p_0, back, ((x0, x1), (y0, y1))) if abs(d) > 1e-12
                 for lim in lims]
        reach = min(t for t in steps if t > 0)
        ends = np.array([cov.p_0 + 2 * cov.obstacle_radius * back, cov.p_0 + reach * back])
        ax.plot(ends[:, 0], ends[:, 1], "m--", lw=1.0, label="K" if i == 0 else None)
    ax.plot(*scene.p_T, "k*", ms=9)
    ax.set_xlim(x0, x1), ax.set_ylim(y0, y1), ax.set_aspect("equal")


def _cells(ax, g, values, vmax, cmap):
    cm = plt.get_cmap(cmap)
    for (_, r), v in zip(g.iterrows(), values):
        if np.isfinite(v):
            ax.add_patch(Rectangle((r.x0, r.y0), r.x1 - r.x0, r.y1 - r.y0, color=cm(min(v, vmax) / vmax), lw=0))


def bracket_figure(scene, df, paths, bs, stem, formats):
    names = list(df.controller.unique())
    fig, axes = plt.subplots(2, len(names), figsize=(5.2 * len(names), 6.6), squeeze=False)
    for j, name in enumerate(names):
        g = df[df.controller == name]
        top, bottom = axes[0, j], axes[1, j]
        _cells(top, g, g.eps_lo.to_numpy(float), max(bs.eps), "Greens")
        with_map = bool(g.certified_map.any())
        for _, r in g[g.certified_map.astype(bool)].iterrows():
            top.add_patch(Rectangle((r.x0, r.y0), r.x1 - r.x0, r.y1 - r.y0, fill=False, ec="tab:blue", lw=0.4,
                                    hatch="////"))
        _scene(top, scene)
        top.set_title(f"{name}: ε_lo (certified; white: none)"
                      + (f"\nhatched: with the map's ε̄ ({int(g.certified_map.sum())} cells)" if with_map else ""))
        eh = g.eps_hi.to_numpy(float)
        _cells(bottom, g, np.where(np.isfinite(eh), eh, np.nan), bs.eps_max, "Reds_r")
        fm = g.falsified_map.astype(bool) if "falsified_map" in g else np.zeros(len(g), bool)
        for _, r in g[fm].iterrows():
            bottom.add_patch(Rectangle((r.x0, r.y0), r.x1 - r.x0, r.y1 - r.y0, fill=False, ec="tab:purple", lw=0.4,
                                       hatch="\\\\"))
        _scene(bottom, scene)
        bottom.set_title(f"{name}: ε_hi (falsified; white: none ≤ {bs.eps_max:g})"
                         + (f"\nhatched: within the map's ε̄ ({int(fm.sum())} cells)" if fm.any() else ""))
        order = np.argsort(np.where(np.isfinite(eh), eh, np.inf))[:4]
        for k in order:
            if np.isfinite(eh[k]):
                p = paths[name][:, g.index[k] - g.index[0]]
                bottom.plot(p[:, 0], p[:, 1], "b-", lw=0.8)
    axes[0, 0].legend(loc="lower left", fontsize=7)
    fig.tight_layout()
    for fmt in formats:
        fig.savefig(f"{stem}.{fmt}", dpi=110)
    plt.close(fig)
