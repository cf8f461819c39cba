"""The certified error map's figures and table (docs/certify.md): certified `eps_bar` beside the sampled error per
`kappa` (heat maps, log colour scale), the tightness map `eps_bar / eps_emp`, Assumption 1's coverage curve from
both, and table.md."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib import pyplot as plt
from matplotlib.colors import LogNorm

from pipeline.viz import save


def _heat(ax, values, extent, norm, title, region=None):
    im = ax.imshow(np.where(np.isfinite(values), np.maximum(values, norm.vmin), np.nan), origin="lower",
                   extent=extent, norm=norm, cmap="viridis", interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_aspect("equal")
    if region is not None:  # a region's map: drawn at its own scale (1 unit around it)
        (rx0, rx1), (ry0, ry1) = region
        ax.set_xlim(rx0 - 1.0, rx1 + 1.0)
        ax.set_ylim(ry0 - 1.0, ry1 + 1.0)
    return im


def write_figures(folder: Path, fields: dict, summary: dict, arena, formats) -> list[str]:
    (x0, x1), (y0, y1) = arena
    extent = (x0, x1, y0, y1)
    kappas = list(summary["kappas"])
    emp = fields.get("emp_0")
    panels = [(fields[f"eps_{k}"], f"certified ε̄(P), κ = {k}") for k in kappas]
    if emp is not None:
        panels.insert(0, (emp, f"sampled ε_emp(P) ({summary['samples']} positions per cell)"))
    vals = np.concatenate([np.ravel(v)[np.isfinite(np.ravel(v))] for v, _ in panels])
    norm = LogNorm(vmin=max(float(np.percentile(vals, 1)), 1e-3), vmax=max(float(vals.max()), 1e-2))
    region = summary.get("region")
    fig, axes = plt.subplots(len(panels), 1, figsize=(7, (3.2 if region is None else 2.0) * len(panels)),
                             squeeze=False)
    for ax, (v, title) in zip(axes[:, 0], panels):
        im = _heat(ax, v, extent, norm, title, region)
    fig.colorbar(im, ax=axes[:, 0].tolist(), label="error bound (world units)")
    out = save(fig, folder / "certified_error_map", formats)
    plt.close(fig)
    if emp is not None:
        tight = fields["eps_0"] / np.maximum(emp, 1e-12)
        fig, ax = plt.subplots(figsize=(7, 3.4))
        finite = tight[np.isfinite(tight)]
        im = _heat(ax, tight, extent, LogNorm(vmin=1.0, vmax=max(float(finite.max()), 1.01)),
                   f"tightness ε̄ / ε_emp (κ = 0): median {np.median(finite):.2f}", region)
        fig.colorbar(im, ax=ax)
        out += save(fig, folder / "tightness_map", formats)
        plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 3.6))
    curves = [(fields[f"eps_{k}"], f"certified, κ = {k}") for k in kappas]
    if emp is not None:
        curves.insert(0, (emp, "sampled (estimate)"))
    for v, label in curves:
        e = np.sort(v[np.isfinite(v)])
        ax.step(e, np.arange(1, len(e) + 1) / len(e), where="post", label=label)
    ax.axvline(summary["margin_c_minus_r"], color="k", ls=":", label="c - r (hybrid's tolerated error)")
    ax.set_xscale("log")
    ax.set_xlabel("ε (world units)")
    ax.set_ylabel("covered fraction of the region's operational cells" if summary.get("region") is not None
                  else "covered fraction of the operational set")
    ax.set_title("Assumption 1's coverage: cells with bound ≤ ε", fontsize=9)
    ax.legend(fontsize=8)
    out += save(fig, folder / "coverage_curve", formats)
    plt.close(fig)
    return out


def scope(region, n_cells: int | None = None) -> str:
    """What the cells cover, for the reader: "the operational set", or the region's operational cells when a
    `region` `[[x0, x1], [y0, y1]]` was given."""
    if region is None:
        return "the operational set"
    (x0, x1), (y0, y1) = region
    cells = "" if n_cells is None else f"{n_cells} "
    return f"the region x in [{x0:g}, {x1:g}], y in [{y0:g}, {y1:g}] (its {cells}operational cells)"


def _pgd(a: dict | None) -> str:
    if not a:
        return "-"
    out = f"{a['violations']} of {4 * a['cells']} / max {a['share_max']:.0%}, median {a['share_median']:.0%}"
    if "render_share_max" in a:  # κ = 0: the search over real renders beside the relaxed set's PGD
        out += f"; real renders: {a['render_violations']} past, max {a['render_share_max']:.0%}, median " \
               f"{a['render_share_median']:.0%}"
    return out


def write_table(path: Path, summary: dict) -> None:
    head = ("| κ | certified mean | p95 | max | sampled p95 | sampled max | tightness median | p95 | "
            "max ε̄ < c - r | PGD: past the bound / reach of it | cells | depth counts | seconds |")
    rows = [head, "|" + "---|" * 13]
    for k, r in summary["kappas"].items():
        e, emp, t = r["eps_bar"], r.get("eps_emp"), r.get("tightness")
        f = lambda d, key: f"{d[key]:.3g}" if d else "-"  # noqa: E731
        rows.append(f"| {k} | {e['mean']:.3g} | {e['p95']:.3g} | {e['max']:.3g} | {f(emp, 'p95')} | "
                    f"{f(emp, 'max')} | {f(t, 'median')} | {f(t, 'p95')} | "
                    f"{'yes' if r['theorem1']['holds'] else 'no'} ({r['theorem1']['margin_c_minus_r']:.3g}) | "
                    f"{_pgd(r.get('pgd'))} | {e['n']} | {r['depth']} | {r['seconds']:.0f} |")
    for k, r in summary["kappas"].items():
        if "heading_bar_deg" in r:
            h, he = r["heading_bar_deg"], r.get("heading_emp_deg")
            rows.append(f"\nHeading (κ = {k}, {summary.get('headings')} intervals of [-π, π] per cell): certified "
                        f"median {h['median']:.3g}°, p95 {h['p95']:.3g}°, max {h['max']:.3g}°"
                        + (f"; sampled p95 {he['p95']:.3g}°, max {he['max']:.3g}°" if he else "") + ".")
    path.write_text(f"# Certified error map of {summary['name']}-{summary['model']['id']}\n\n"
                    f"Position head {summary['model'].get('position_head', 'flat')} "
                    f"({summary['model'].get('outputs', 'position')} map); "
                    f"cells of {summary['cell']:g} units over {scope(summary.get('region'), summary['n_cells'])}, "
                    f"mode {summary['mode']}, "
                    f"tolerance {summary['tolerance']:g}, max depth {summary['max_depth']}.\n\n"
                    + "\n".join(rows) + "\n")
