"""Stage: the bracket `[ε_lo, ε_hi]` per controller and start cell (`python -m pipeline.bracket`; docs/bracket.md).

Writes to the Hydra run dir: `bracket.csv` (one row per controller and start cell: `x0, x1, y0, y1`, `start` (the
cell holds starts the simulator accepts: not wholly in the diamond), `eps_lo` (the largest uniform ε certified
within `sim.horizon`; NaN: none), `funnel` (certified there through its sub-squares' funnels,
:mod:`pipeline.bracket.funnel`), `arrival_bound` (seconds: the certified arrival bound at that ε),
`arrival_nominal` (seconds: the falsifier's start without error), `certified_map` (certified with the error map's
ε̄, when given; then also `map_arrival_bound` (seconds, that certificate's), `clouds_p_fail` (with a clouds table:
the bound on the run's failure over the clouds, :mod:`pipeline.bracket.clouds`), `falsified_map`, a run from the
cell's centre failed under every adversary's error within the map's `ε̄` at each frame's position, `map_adversary`
and `map_scale_hi`, the smallest scale of that bound found failing), `eps_hi` (inf: no failure found up to
`eps_max`; NaN: no start), the adversary and outcome of the counterexample; with `bracket.camera_map` also `kappa_hi` (the falsifier through the camera, pixel levels; inf: none up to `kappa_max`),
`camera_adversary`, `camera_outcome`; with both maps `kappa_lo`, `bracket.error_map_kappa` where certified with the
map's ε̄), `table.md` (the bracket table), `certificate.json` (the abstraction's sizes
and counts per controller and ε), `counterexamples.npz` (the paths; `<controller>_map`: within the
map's ε̄; `<controller>_camera`: through the camera) and
`bracket.png`.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from pipeline import tracking
from pipeline.bracket.bounds import Uniform
from pipeline.bracket.certify_loop import certify, funnel_starts
from pipeline.bracket.falsifier import ADVERSARIES, MapBound, Search, attack, falsify
from pipeline.bracket.loop import OUTCOMES, REACHED, RUNNING, FrameLoop
from pipeline.bracket.lost import LostFrames, lost_frames
from pipeline.bracket.maps import camera_map_folder, error_map
from pipeline.bracket.report import table
from pipeline.bracket.starts import axis_distance, axis_starts, falsifier_starts, start_cells, worst_starts
from pipeline.config import build
from pipeline.errors import ConfigError
from pipeline.experiments.report import markdown_table
from pipeline.sim.composed import loop_parts
from pipeline.sim.simulator import stall_threshold


def objects(cfg: DictConfig):
    """(scene, {name: law}, settings, sim, camera, error map or None, camera map folder or None, {name: the lost
    frames the proof covers}), built and checked before any work."""
    parts = loop_parts(cfg)  # the one builder of the loop (pipeline.sim.composed): the single integrator here
    scene, sim, camera = parts.scene, parts.sim, parts.camera
    if scene.barrier.kind != "squared":
        raise ConfigError("scene.barrier.kind", "the bracket's enclosures model the squared barrier (SPEC §5.5's "
                                                f"scope), got {scene.barrier.kind!r}")
    bs = build(cfg.bracket, "bracket")
    laws = {name: parts.law(cfg.controller if name == "hybrid" else cfg.controllers[name],
                            "controller" if name == "hybrid" else f"controllers.{name}") for name in bs.controllers}
    hybrid = laws.get("hybrid")
    if hybrid is not None:  # the enclosures model §3.3's law: a rule they do not model would make a certificate unsound
        if getattr(hybrid, "theta", None) is not None:
            raise ConfigError("controller.noise_tolerance", "the bracket's abstraction models §3.3's mode decisions, "
                                                            "not the side hysteresis: null here")
        if getattr(hybrid, "saturation", "radial") != "radial":
            raise ConfigError("controller.saturation", "the bracket's input enclosures model the radial saturation "
                                                       "(§3.3's flow scaled to u_max): radial here")
    if camera.period is None:
        raise ConfigError("camera.period", "the bracket needs a frame period (the sampled loop), got null")
    lost = lost_frames(sim, camera, bs, laws)
    cam_folder = camera_map_folder(cfg, bs, scene)
    return scene, laws, bs, sim, camera, error_map(cfg, bs, scene.bounds, cam_folder), cam_folder, lost


def check(cfg: DictConfig) -> None:
    objects(cfg)


def nominal_arrival(loop: FrameLoop, p0: np.ndarray) -> np.ndarray:
    """Seconds to the goal disc of the runs from `p0` without error (NaN: did not arrive within the horizon)."""
    st = loop.start(p0, np.zeros_like(p0))
    zero = np.zeros_like(p0)
    while (st["outcome"] == RUNNING).any():
        st = loop.step(st, zero)
    return np.where(st["outcome"] == REACHED, st["t_end"], np.nan)


def progress(name: str, what: str, t0: float) -> None:
    """One line per finished phase of a law (a certificate at one ε, the falsifier), so that a run of several minutes
    shows where it is (flushed: the laws' processes share the terminal)."""
    print(f"bracket: {name}: {what} ({time.perf_counter() - t0:.0f} s)", flush=True)


def bracket_rows(name, law, scene, bs, sim, camera, emap, starts, pmap=None, lost: LostFrames | None = None):
    """One controller: the certificate at each ε (and the map's ε̄) within the horizon and with the lost frames of
    `lost`, the falsifier (and through the camera of `pmap`, a loaded perception map); rows, stats, paths, camera
    paths (None without `pmap`)."""
    loop = FrameLoop(scene, law, period=camera.period, horizon=sim.horizon, delta=bs.goal_radius,
                     stall_speed=stall_threshold(sim, law), stall_time=sim.stall_time)
    kw = dict(h=bs.cell, angle=bs.angle, period=camera.period, goal_radius=bs.goal_radius, n_split=bs.n_split,
              window=bs.window, frames=bs.frames, horizon=loop.n_frames, lost=lost, funnels=bs.funnel_split > 0,
              refine_half=bs.refine, refine_factor=bs.refine_factor, directional=bs.directional)
    eps_lo, arrival = np.full(len(starts), np.nan), np.full(len(starts), np.nan)
    stats, funnel = {}, np.full(len(starts), False)
    fw = dict(split=bs.funnel_split, period=camera.period, horizon=loop.n_frames, lost=lost,
              polytope_split=bs.polytope_split, mode_split=bs.mode_split)
    for eps in bs.eps:
        t0 = time.perf_counter()
        cert = certify(law, Uniform(eps), **kw)
        ok, frames, no_start, by_funnel = funnel_starts(cert, law, starts, **fw)
        eps_lo[ok], arrival[ok] = eps, np.maximum(frames[ok], 1) * camera.period  # arrival is told at a frame's end
        funnel[ok] = by_funnel[ok]
        stats[f"eps={eps:g}"] = {**cert.stats, "certified_starts": int(ok.sum()), "by_funnel": int(by_funnel.sum()),
                                 "seconds": time.perf_counter() - t0}
        progress(name, f"ε = {eps:g}: certified {int(ok.sum())}/{int((~no_start).sum())} start cells", t0)
    by_map, map_frames = np.full(len(starts), False), None
    if emap is not None:
        t0 = time.perf_counter()
        cert = certify(law, emap, **kw)
        by_map, map_frames, _, by_funnel = funnel_starts(cert, law, starts, **fw)
        progress(name, f"the map's ε̄: certified {int(by_map.sum())} start cells", t0)
        stats["error_map"] = {**cert.stats, "certified_starts": int(by_map.sum()), "by_funnel": int(by_funnel.sum()),
                              **({"clouds": emap.clouds.summary()} if hasattr(emap, "clouds") else {})}
    if lost is not None and lost.max_lost > 0:
        stats["lost_frames"] = {"model": lost.describe(), "p_fail": camera.p_fail,
                                "p_more_per_run": lost.p_more(camera.p_fail, loop.n_frames)}
    search = Search(n_dirs=bs.n_dirs, lookahead=bs.lookahead, commit=bs.commit, tail=bs.tail,
                    n_random=bs.n_random, seed=bs.seed, trap_dirs=bs.trap_dirs, trap_reach=bs.trap_reach,
                    trap_offset=bs.trap_offset)
    centres, inside = falsifier_starts(scene, starts)
    inside &= ~no_start
    t0 = time.perf_counter()
    br = falsify(loop, centres[inside], bs.eps_max, bs.n_bisect, search)
    stats["falsifier_seconds"] = time.perf_counter() - t0
    progress(name, f"falsifier: {int(np.isfinite(br.eps_hi).sum())}/{int(inside.sum())} start cells broken", t0)
    t_sim = np.full(len(starts), np.nan)
    t_sim[inside] = nominal_arrival(loop, centres[inside])
    eps_hi = np.full(len(starts), np.nan)  # no falsifier run: the cell holds no start the simulator accepts
    adv, out = np.full(len(starts), "no start", dtype=object), np.full(len(starts), "", dtype=object)
    eps_hi[inside], adv[inside] = br.eps_hi, br.adversary
    out[inside] = [OUTCOMES[o] if np.isfinite(e) else "" for o, e in zip(br.outcome, br.eps_hi)]
    paths = np.full((br.path.shape[0], len(starts), 2), np.nan)
    paths[:, inside] = br.path
    hi_start = np.where(inside[:, None], centres, np.nan)
    if bs.axis_start > 0:  # the falsifier again from the points nearest K: the smaller ε_hi kept
        stats["axis_falsifier"] = ax = axis_falsifier(loop, scene, starts, centres, inside, bs, search, {
            "eps_hi": eps_hi, "adversary": adv, "outcome": out, "paths": paths, "start": hi_start})
        progress(name, f"nearest K: ε_hi lowered on {ax['lowered']}/{ax['starts']}", time.perf_counter() - ax["seconds"])
    rows = pd.DataFrame({"controller": name, "x0": starts[:, 0], "x1": starts[:, 1], "y0": starts[:, 2],
                         "y1": starts[:, 3], "start": ~no_start, "eps_lo": eps_lo, "funnel": funnel,
                         "arrival_bound": arrival,
                         "arrival_nominal": t_sim, "certified_map": by_map, "eps_hi": eps_hi, "adversary": adv,
                         "outcome": out, "hi_x": hi_start[:, 0], "hi_y": hi_start[:, 1]})
    more = {}
    if emap is not None:
        t0 = time.perf_counter()
        cols, more["map"] = map_columns(loop, scene, starts, emap, search, centres, inside, bs, (br.eps_hi, br.path))
        stats["map_falsifier_seconds"] = time.perf_counter() - t0
        frames = np.where(by_map, np.maximum(map_frames, 1), np.nan)  # the map's certified arrival bound
        rows["map_arrival_bound"] = frames * camera.period
        if hasattr(emap, "clouds"):  # a clouds table: the run's failure over the clouds (pipeline.bracket.clouds)
            rows["clouds_p_fail"] = emap.clouds.p_fail(frames, lost.max_lost if lost else 0, camera.p_fail)
        for k, v in cols.items():
            rows[k] = v
    if pmap is not None:
        t0 = time.perf_counter()
        cols, more["camera"] = camera_rows(loop, pmap, bs, centres, inside)
        stats["camera_falsifier_seconds"] = time.perf_counter() - t0
        for k, v in cols.items():
            rows[k] = v
        if emap is not None:  # the map's ε̄ at error_map_kappa holds for every frame within that many levels
            rows["kappa_lo"] = np.where(by_map, bs.error_map_kappa, np.nan)
    return rows, stats, paths, more


def map_columns(loop: FrameLoop, scene, starts, emap, search: Search, centres, inside, bs, uniform):
    """:func:`map_rows` from the cells' centres, then where the map's bound is largest
    (:func:`.starts.worst_starts`, where it is larger than at the centre), then the points nearest `K`."""
    worst, b_worst = worst_starts(scene, starts, MapBound(emap))
    worst[~(b_worst > MapBound(emap)(centres))] = np.nan  # only where the bound is larger than at the centre
    near_k, d_k = axis_starts(scene, starts)
    near_k[~np.isfinite(d_k)] = np.nan
    return map_rows(loop, emap, search, centres, inside, bs.map_bisect, uniform, (worst, near_k))


def axis_falsifier(loop: FrameLoop, scene, starts, centres, inside, bs, search: Search, hi: dict) -> dict:
    """The uniform falsifier again from the start cells' points nearest `K` (:func:`.starts.axis_starts`) within
    `bs.axis_start` of it and nearer than the centre; where it fails at a smaller `ε`, the columns `hi` (`eps_hi`,
    `adversary`, `outcome`, `paths`, `start`: over all cells) take its counterexample. The hybrid law's trap on `K`
    needs less error from a cell's edge nearest the axis (docs/bracket.md, "The start cells near the axis")."""
    t0 = time.perf_counter()
    near_k, d_k = axis_starts(scene, starts)
    rows = np.flatnonzero(inside & (d_k <= bs.axis_start) & (d_k < axis_distance(scene, centres) - 1e-9))
    lowered = np.zeros(0, int)
    if rows.size:
        bk = falsify(loop, near_k[rows], bs.eps_max, bs.n_bisect, search)
        k = bk.eps_hi < hi["eps_hi"][rows]
        lowered = rows[k]
        hi["eps_hi"][lowered], hi["adversary"][lowered] = bk.eps_hi[k], bk.adversary[k]
        hi["outcome"][lowered] = [OUTCOMES[o] for o in bk.outcome[k]]
        hi["paths"][:, lowered], hi["start"][lowered] = bk.path[:, k], near_k[lowered]
    return {"starts": int(len(rows)), "lowered": int(len(lowered)), "seconds": time.perf_counter() - t0}


def map_rows(loop: FrameLoop, emap, search: Search, centres: np.ndarray, inside: np.ndarray, n_bisect: int,
             uniform: tuple[np.ndarray, np.ndarray] | None = None, alts=()) -> tuple[dict, np.ndarray]:
    """Every adversary with the error map's own bound (:class:`MapBound`: its `ε̄` at the true position each frame, 0
    where it is certified nowhere) from the start cells' centres: the columns `falsified_map` (a run failed: no
    certificate from this map's bound can hold there), `map_adversary` and `map_scale_hi` (the smallest scale `s` of
    the bound found failing, bisected on `(0, 1]` in `n_bisect` steps after the run without error (0: the nominal
    run fails, an error the bound allows too); the map's `ε̄` is `1/s` times what this counterexample needs; NaN: not
    falsified), `map_eps_start` (the map's `ε̄` at the falsifier's start; inf: the map is certified nowhere there),
    `map_x, map_y` (that start) and the paths `(frames + 1, cells, 2)` at that scale. `uniform`: the uniform
    falsifier's `(ε_hi, paths)` of the same starts; a counterexample whose path keeps the map's bound at least `ε_hi`
    at every frame is one within the map's bound as it is (its errors are at most `ε_hi`): falsified without a
    search (`map_adversary` "uniform"), at scale `max ε_hi / ε̄` along the path, not bisected further. `alts`: per
    start cell further starts `(cells, 2)` each, searched in turn where the searches before found nothing (the
    stage's: :func:`.starts.worst_starts`, where the map's bound is largest, then :func:`.starts.axis_starts`, the
    point nearest `K`; a row of NaN: none). A certificate claims every start of its cell."""
    p0 = centres[inside].copy()
    bound = MapBound(emap)
    failed, which = np.zeros(len(p0), bool), np.full(len(p0), -1)
    scale, path = np.full(len(p0), np.nan), np.full((loop.n_frames + 1, len(p0), 2), np.nan)

    def tried(p: np.ndarray, rows: np.ndarray, s: float) -> np.ndarray:  # from p[rows] at scale s (0: no error)
        f, w, _, pth = attack(loop, p[rows], MapBound(emap, s), search, adversaries=ADVERSARIES[:1] if s == 0 else ADVERSARIES)
        r = rows[f]
        failed[r], which[r], scale[r], path[:, r] = True, w[f], s, pth[:, f]
        return r

    tried(p0, np.arange(len(p0)), 0.0)  # the run without error: an error every bound allows
    if uniform is not None:  # the uniform counterexamples the map's bound covers as they are
        eps_hi, u_path = uniform
        least = bound(u_path.reshape(-1, 2)).reshape(u_path.shape[:2]).min(axis=0)  # every frame at once
        with np.errstate(invalid="ignore", divide="ignore"):
            s_u = np.where(least > 0, eps_hi / least, np.where(eps_hi == 0, 0.0, np.inf))
        take = ~failed & np.isfinite(eps_hi) & (s_u <= 1.0)
        failed[take], which[take], scale[take], path[:, take] = True, len(ADVERSARIES), s_u[take], u_path[:, take]
    tried(p0, np.flatnonzero(~failed), 1.0)
    for alt in alts:  # other starts the certificate claims too, where nothing failed yet
        alt = alt[inside]
        rows = np.flatnonzero(~failed & np.isfinite(alt).all(axis=1) & (alt != p0).any(axis=1))
        r = np.concatenate([tried(alt, rows, 0.0), tried(alt, rows[~failed[rows]], 1.0)])
        p0[r] = alt[r]
    lo = np.zeros(len(p0))
    searched = failed & (scale == 1.0)  # found by the search at the map's bound: bisected (the others have a scale)
    for _ in range(n_bisect):
        mid = 0.5 * (lo + scale)
        for s in np.unique(mid[searched]):  # the rows at one scale run together
            rows = np.flatnonzero(searched & (mid == s))
            f, w, _, pth = attack(loop, p0[rows], MapBound(emap, s), search)
            scale[rows[f]], which[rows[f]], path[:, rows[f]] = s, w[f], pth[:, f]
            lo[rows[~f]] = s
    n = len(centres)
    fals, scale_all = np.zeros(n, bool), np.full(n, np.nan)
    adv = np.full(n, "", dtype=object)
    fals[inside], scale_all[inside] = failed, scale
    adv[inside] = [("uniform" if a == len(ADVERSARIES) else ADVERSARIES[a]) if a >= 0 else "" for a in which]
    paths = np.full((path.shape[0], n, 2), np.nan)
    paths[:, inside] = path
    at_start, start = np.full(n, np.nan), np.full((n, 2), np.nan)
    at_start[inside], start[inside] = emap.at(p0), p0
    return {"falsified_map": fals, "map_adversary": adv, "map_scale_hi": scale_all, "map_eps_start": at_start,
            "map_x": start[:, 0], "map_y": start[:, 1]}, paths


def camera_rows(loop: FrameLoop, pmap, bs, centres: np.ndarray, inside: np.ndarray) -> tuple[dict, np.ndarray]:
    """The falsifier through the camera of `pmap` from the start cells' centres outside the obstacle: the columns
    `kappa_hi`, `camera_adversary`, `camera_outcome` and the paths `(frames + 1, start cells, 2)`."""
    from pipeline.bracket.camera_falsifier import (  # torch: not in preflight
        CameraLoop,
        CameraSearch,
        falsify_camera,
    )

    search = CameraSearch(steps=bs.pgd_steps, n_dirs=bs.n_dirs, device=str(pmap.device))
    cb = falsify_camera(CameraLoop(loop, pmap.net, pmap.camera(), search), centres[inside], bs.kappa_max,
                        tuple(bs.camera_adversaries))
    n = len(centres)
    kappa_hi = np.full(n, np.nan)
    adv, out = np.full(n, "no start", dtype=object), np.full(n, "", dtype=object)
    kappa_hi[inside], adv[inside] = cb.kappa_hi, cb.adversary
    out[inside] = [OUTCOMES[o] if np.isfinite(k) else "" for o, k in zip(cb.outcome, cb.kappa_hi)]
    paths = np.full((cb.path.shape[0], n, 2), np.nan)
    paths[:, inside] = cb.path
    return {"kappa_hi": kappa_hi, "camera_adversary": adv, "camera_outcome": out}, paths


CODE = ("bracket", "control", "sim", "plants.py")  # the code the bracket's numbers depend on (its id)


def bracket_id(cfg: DictConfig, bs, emap, cam_folder: Path | None = None) -> tuple[str, dict]:
    """The output's id: what determines its bytes (the scene, the compared laws' nodes, the camera period, the sim,
    the bracket's settings, the error map's cells and bounds, the camera map's id, the code); and the manifest's
    record of it."""
    laws = {n: tracking.to_plain(cfg.controller if n == "hybrid" else cfg.controllers[n]) for n in bs.controllers}
    parts = {"scene": tracking.to_plain(cfg.scene), "controllers": laws, "camera": tracking.to_plain(cfg.camera),
             "sim": tracking.to_plain(cfg.sim),
             "bracket": {**tracking.to_plain(cfg.bracket), "error_map": None, "camera_map": None},
             "camera_map": None if cam_folder is None else cam_folder.name,
             "error_map": None if emap is None else hashlib.sha256(np.ascontiguousarray(emap.cells).tobytes()).hexdigest(),
             "clouds": getattr(emap, "clouds", None) and emap.clouds.summary(),
             "code": tracking.code_version(*CODE)}
    return tracking.content_id(parts), {**parts, "error_map_ref": bs.error_map, "camera_map_ref": bs.camera_map}


def law_workers(n_laws: int) -> int:
    """Processes for the laws side by side: the job's share of the cores (`OMP_NUM_THREADS`, which `make paper`
    sets per job; else every core this process may use), at most one per law."""
    cores = os.environ.get("OMP_NUM_THREADS")
    if cores and cores.isdigit():
        cores = int(cores)
    else:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, min(n_laws, cores))


def each_law(laws: dict, scene, bs, sim, camera, emap, starts, pmap, lost):
    """`(name, bracket_rows(...))` per law in the laws' order, as each is done: side by side in spawned processes
    (:func:`law_workers`; each law's rows depend on nothing else, so the bytes are the same), or one after another
    with a camera map (its torch network stays in this process)."""
    workers = law_workers(len(laws)) if pmap is None else 1
    if workers == 1:
        for name, law in laws.items():
            yield name, bracket_rows(name, law, scene, bs, sim, camera, emap, starts, pmap, lost[name])
        return
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {name: pool.submit(bracket_rows, name, law, scene, bs, sim, camera, emap, starts, None, lost[name])
                   for name, law in laws.items()}
        for name, future in futures.items():
            yield name, future.result()


def run(cfg: DictConfig) -> dict:
    scene, laws, bs, sim, camera, emap, cam_folder, lost = objects(cfg)
    id_, meta = bracket_id(cfg, bs, emap, cam_folder)
    final = Path(cfg.paths.bracket_dir) / f"bracket-{id_}"
    if tracking.is_complete(final) and not cfg.get("force", False):
        df = pd.read_csv(final / "bracket.csv", float_precision="round_trip")
        print(f"bracket: {final} is complete (force=true to recompute)\n{(final / 'table.md').read_text()}")
        return {"bracket": df, "table": None, "stats": json.loads((final / "certificate.json").read_text()),
                "path": final, "skipped": True}
    starts = start_cells(scene, bs.start_cell)
    pmap = None
    if cam_folder is not None:
        from pipeline.perception.maps import load_perception_map  # torch: not in the preflight

        pmap = load_perception_map(cam_folder, models_dir=cfg.paths.models_dir, device=bs.camera_device)
    frames, stats, paths, cam_paths = [], {}, {}, {}
    for name, (rows, st, pth, more) in each_law(laws, scene, bs, sim, camera, emap, starts, pmap, lost):
        frames.append(rows)
        stats[name], paths[name] = st, pth
        cam_paths.update({f"{name}_{kind}": p for kind, p in more.items()})
        print(f"bracket: {name}: certified at the largest ε {int(rows.eps_lo.notna().sum())}/{len(rows)} start "
              f"cells, falsified {int(np.isfinite(rows.eps_hi).sum())}/{len(rows)}"
              + (f", with the map's ε̄ certified {int(rows.certified_map.sum())}, falsified "
                 f"{int(rows.falsified_map.sum())}" if "falsified_map" in rows else "")
              + (f", through the camera {int(np.isfinite(rows.kappa_hi).sum())}/{len(rows)}" if "camera" in more
                 else ""), flush=True)
    df = pd.concat(frames, ignore_index=True)
    tab = table(df, scene, bs.eps, with_map=emap is not None)
    from pipeline.bracket.figures import bracket_figure  # matplotlib: not imported by the preflight

    with tracking.tracked_output(final.parent, "bracket", id_, {"kind": "bracket", "recipe": meta}) as tmp:
        df.to_csv(tmp / "bracket.csv", index=False)
        (tmp / "table.md").write_text(markdown_table(tab) + "\n")
        (tmp / "certificate.json").write_text(json.dumps(stats, indent=1, default=float))
        np.savez_compressed(tmp / "counterexamples.npz",
                            **{k: v.astype(np.float32) for k, v in {**paths, **cam_paths}.items()})
        bracket_figure(scene, df, paths, bs, tmp / "bracket", bs.formats)
    print(markdown_table(tab))
    print(f"bracket -> {final}")
    return {"bracket": df, "table": tab, "stats": stats, "path": final, "skipped": False}

