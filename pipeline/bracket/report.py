"""The bracket table (docs/bracket.md, "Results"): per controller, over the start cells of `bracket.csv`."""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.bracket.starts import behind_obstacles


def table(df: pd.DataFrame, scene, eps_list, with_map: bool = False) -> pd.DataFrame:
    """Per controller, over the start cells holding a start the simulator accepts (`start`; the others, inside the
    diamond, are counted apart): certified share at each ε (within the horizon), falsified shares, the share still
    undecided at the largest ε (neither certified at it nor falsified up to it), behind an obstacle (its frame
    coordinate `a < -c`, `|b| < 15`), the median `ε_hi` on `K` (the cells the axis behind an obstacle passes
    through); the certified arrival bound beside the nominal run's arrival (seconds, medians over certified cells)
    and the certified cells whose nominal run arrives later than the bound (a soundness bug); with a `kappa_hi`
    column, the share falsified through the camera and the median `κ_hi` on `K`; with the error map, the shares
    certified, falsified (a run failed with errors within the map's `ε̄`; the median scale of that bound still
    failing) and undecided with its bound, and the cells both certified and falsified with it (a soundness bug);
    with a clouds table (:mod:`.clouds`), the median and least bound on a certified start's failure over the clouds;
    with the map and the camera, the start cells certified through the camera (`κ_lo`: with the map's `ε̄` at
    the pixel budget `bracket.error_map_kappa`, every frame within `κ_lo` levels of the rendered one) and those of
    them the camera falsifier breaks at a budget `κ_hi <= κ_lo` (a soundness bug of the chain: map bound,
    certificate)."""
    behind, on_K = behind_obstacles(df, scene)
    start = df["start"].to_numpy(bool) if "start" in df else np.ones(len(df), bool)
    out = []
    for name, whole in df.groupby("controller", sort=False):
        g = whole[start[whole.index]]
        row = {"controller": name, "start cells": f"{len(g)}" + (f" (+{len(whole) - len(g)} in the diamond)"
                                                                 if len(whole) > len(g) else "")}
        for eps in eps_list:
            row[f"certified ε={eps:g}"] = f"{(g.eps_lo >= eps).mean():.0%}"
        for eps in eps_list:
            row[f"falsified ε<={eps:g}"] = f"{(g.eps_hi <= eps).mean():.0%}"
        top_eps = max(eps_list)  # the bracket still open there: neither certified at it nor falsified up to it
        row[f"undecided at ε={top_eps:g}"] = f"{(~(g.eps_lo >= top_eps) & ~(g.eps_hi <= top_eps)).mean():.0%}"
        bh = g[behind[g.index]]
        top = f" (ε_lo up to {bh.eps_lo.max():g})" if bh.eps_lo.notna().any() else ""
        row["behind: certified"] = f"{int(bh.eps_lo.notna().sum())}/{len(bh)}{top}"
        k = g[on_K[g.index]]
        row["on K: median ε_hi"] = f"{np.nanmedian(k.eps_hi):.3g}" if k.eps_hi.notna().any() else "-"
        if "arrival_bound" in g:
            c = g[g.eps_lo.notna()]
            row["arrival (s): bound / nominal"] = (f"{c.arrival_bound.median():.3g} / {c.arrival_nominal.median():.3g}"
                                                   if len(c) else "-")
        if "kappa_hi" in g:
            row["camera: falsified"] = f"{np.isfinite(g.kappa_hi).mean():.0%}"
            row["on K: median κ_hi"] = f"{np.nanmedian(k.kappa_hi):.3g}" if k.kappa_hi.notna().any() else "-"
        row["map ε̄: certified"] = (f"{g.certified_map.mean():.0%} ({int(bh.certified_map.sum())}/{len(bh)} behind)"
                                    if with_map else "-")
        if with_map and "falsified_map" in g:
            cm, fm = g.certified_map.astype(bool), g.falsified_map.astype(bool)
            sc = f", median scale {g.map_scale_hi[fm].median():.2g}" if "map_scale_hi" in g and fm.any() else ""
            row["map ε̄: falsified"] = (f"{fm.mean():.0%} ({int(bh.falsified_map.astype(bool).sum())}/{len(bh)} "
                                        f"behind{sc})")
            und = ~cm & ~fm
            off = (f" ({int((und & ~np.isfinite(g.map_eps_start)).sum())} start where the map has no bound)"
                   if "map_eps_start" in g else "")
            row["map ε̄: undecided"] = f"{und.mean():.0%}{off}"
        if with_map and "clouds_p_fail" in g:  # a clouds table's ε̄_δ: the run's failure over the clouds
            p = g.clouds_p_fail[g.certified_map.astype(bool)]
            row["clouds: P(fail) per run <="] = f"{p.median():.3g} (best {p.min():.3g})" if len(p) else "-"
        row["soundness: ε_lo > ε_hi"] = int((g.eps_lo > g.eps_hi).sum())
        if with_map and "falsified_map" in g:  # a certified start that a run within the map's bound breaks
            row["soundness: map certified and falsified"] = int((cm & fm).sum())
        if "arrival_bound" in g:  # the nominal run is one the certificate covers (no error): it arrives by the bound
            row["soundness: arrival > bound"] = int((g.eps_lo.notna() & ~(g.arrival_nominal <= g.arrival_bound
                                                                          + 1e-9)).sum())
        if with_map and "kappa_hi" in g:  # every frame within κ_lo levels is within the map's certified ε̄ at κ_lo:
            lo = g.kappa_lo if "kappa_lo" in g else g.certified_map.map({True: 0.0, False: np.nan})  # no run fails
            row["camera: certified (κ_lo)"] = (f"{lo.notna().mean():.0%} ({int(lo.notna().sum())} at κ_lo "
                                                f"{np.nanmax(lo):g})" if lo.notna().any() else "0% (none)")
            row["soundness: κ_hi <= κ_lo"] = int((lo.notna() & (g.kappa_hi <= lo)).sum())
        out.append(row)
    return pd.DataFrame(out)
