"""Writers of the paper folder (drawing code: not part of any experiment's cache key): figures (PNG + PDF),
tables (CSV + Markdown + LaTeX) and `index.md`."""

from __future__ import annotations

import json
import re
from fnmatch import fnmatch
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.control import Scene
from pipeline.repo import CONF_DIR, REPO_ROOT, write_atomic
from pipeline.viz import draw_scene, save

# The paper's figures, in its order, then ours (fig8 on): stem -> (experiment id, what it reproduces)
FIGURES = {
    "fig1_perception_closeness": ("perception_closeness", "paper Fig. 1 (closeness)"),
    "fig2_sensitive_set": ("sensitive_set", "paper Fig. 2 (obstacle problem and the set K)"),
    "fig3_coverings": ("coverings", "paper Fig. 3 (coverings)"),
    "fig4_scheme": ("scheme", "paper Fig. 4 (scheme of the closed loop)"),
    "fig5_leader_follower_level_sets": ("leader_follower", "paper Fig. 5 (level sets around the moving target)"),
    "fig6_occlusion": ("occlusion", "paper Fig. 6 (occlusion)"),
    "fig7_robustness_noise_failure": ("noise_failure", "paper Fig. 7 (noise and camera failure)"),
    "fig8_robustness_sweep": ("robustness_sweep", "not in the paper: Proposition 1 vs Theorem 1 measured"),
    "fig9_monte_carlo": ("monte_carlo", "not in the paper: Monte Carlo success rates"),
    "fig10_authors_code_vs_default": ("authors_code", "not in the paper: the authors' released-code scene"),
    "fig11_hysteresis_margin": ("hysteresis_margin", "not in the paper: Theorem 1's robustness margin over (χ, λ)"),
    "fig12_sample_and_hold": ("sample_and_hold", "not in the paper: the 20 Hz sample-and-hold vs continuous time"),
    "fig13_perception_generalisation": ("perception_generalisation",
                                        "not in the paper: every perception map on every cloud level (issue 11)"),
    # make paper's attacks (issue 20), then make multi's (issue 19): one sequence, one index.md
    "fig14_camera_attack": ("camera_attack", "not in the paper: Proposition 1 through the camera (pixel attack)"),
    "fig15_worst_cloud": ("worst_cloud", "not in the paper: the worst cloud layout each frame"),
    "fig16_geometry_margin": ("geometry_margin", "not in the paper: Theorem 1's margin over the geometry"),
    "fig17_multi_cells": ("multi_cells", "not in the paper: several obstacles, the cells of the active one"),
    "fig18_multi_adversarial": ("multi_adversarial", "not in the paper: Proposition 1 behind every obstacle"),
    "fig19_multi_monte_carlo": ("multi_monte_carlo", "not in the paper: Monte Carlo over random valid fields"),
    "fig20_multi_camera": ("multi_camera", "not in the paper: the camera in the loop on a 5-disc field"),
    "fig21_unicycle": ("unicycle", "not in the paper: the unicycle from its pose map"),
    "fig21_unicycle_field": ("unicycle_field", "not in the paper: the unicycle on the 5-disc field"),
    "fig22_dense_fields": ("dense_fields", "not in the paper: the hybrid-RL benchmark's dense clutter"),
    "fig23_dense_unicycle": ("dense_unicycle", "not in the paper: the unicycle in dense clutter"),
    "fig24_dense_camera": ("dense_camera", "not in the paper: the camera in the loop in dense clutter"),
    "fig25_dense_sweep": ("dense_sweep", "not in the paper: 30 benchmark-like fields, each its own covering"),
    "fig26_dense_sweep_unicycle": ("dense_sweep_unicycle",
                                   "not in the paper: the unicycle on 30 benchmark-like fields (issue 45)"),
}


def figure_stem(experiment: str) -> str:
    """The figure stem (`figNN_...`, the one sequence of `make paper` and `make multi`) of an experiment id."""
    return next(stem for stem, (exp, _) in FIGURES.items() if exp == experiment)


# ----------------------------------------------------------------------------------------- writers
def _fmt(v) -> str:
    if isinstance(v, str) and not v:  # as a cached result reads it back (an empty CSV field is NaN): one table
        return "–"
    if isinstance(v, float | np.floating):
        if not np.isfinite(v):
            return "–"
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.0f}"
    return str(v)


def markdown_table(df: pd.DataFrame) -> str:
    head = "| " + " | ".join(map(str, df.columns)) + " |"
    sep = "|" + "|".join("---" for _ in df.columns) + "|"
    body = ["| " + " | ".join(_fmt(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([head, sep, *body]) + "\n"


def latex_table(df: pd.DataFrame, caption: str, label: str) -> str:
    esc = lambda s: str(s).replace("_", r"\_").replace("%", r"\%").replace("&", r"\&")  # noqa: E731
    lines = [r"\begin{table}[t]", r"\centering", rf"\caption{{{esc(caption)}}}", rf"\label{{tab:{label}}}",
             r"\begin{tabular}{" + "l" * len(df.columns) + "}", r"\toprule",
             " & ".join(esc(c) for c in df.columns) + r" \\", r"\midrule"]
    lines += [" & ".join(esc(_fmt(v)) for v in row) + r" \\" for row in df.itertuples(index=False)]
    lines += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(lines) + "\n"


class Outputs:
    """Writes a scenario's figures and tables into the paper folder and records them for index.md."""

    def __init__(self, paper_dir: Path, exp_id: str):
        self.dir = Path(paper_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.exp_id = exp_id
        self.items: list[dict] = []

    def figure(self, fig, stem: str, caption: str) -> list[Path]:
        paths = [Path(p) for p in save(fig, self.dir / stem, formats=("png", "pdf"))]
        self.items.append({"kind": "figure", "files": [p.name for p in paths], "caption": caption,
                           "reproduces": FIGURES.get(stem, (None, None))[1]})
        return paths

    def table(self, df: pd.DataFrame, stem: str, caption: str) -> list[Path]:
        paths = [self.dir / f"{stem}.{ext}" for ext in ("csv", "md", "tex")]
        df.to_csv(paths[0], index=False)
        paths[1].write_text(f"**{caption}**\n\n" + markdown_table(df))
        paths[2].write_text(latex_table(df, caption, stem))
        self.items.append({"kind": "table", "files": [p.name for p in paths], "caption": caption})
        return paths


def publish(paper_dir: Path, entry: dict, figures: dict = FIGURES) -> Path:
    """Record an experiment's entry (`<paper_dir>/index/<id>.json`) and rewrite index.md from every entry, each file
    written whole: `make paper` runs experiments side by side, each reading the others' entries."""
    (Path(paper_dir) / "index").mkdir(parents=True, exist_ok=True)
    write_atomic(Path(paper_dir) / "index" / f"{entry['id']}.json", json.dumps(entry, indent=2) + "\n")
    return write_index(paper_dir, figures)


def write_index(paper_dir: Path, figures: dict = FIGURES) -> Path:
    """index.md from every experiment's entry in `<paper_dir>/index/*.json`, in the paper's figure order
    (`figures`: stem -> (experiment id, what it reproduces)); paths relative to `paper_dir`. Every other file of the
    folder (the lock, the profile, the tables and figures `make paper` copies from the learned and bracket stages,
    the entries themselves) is linked under "Other files", and a gap in the figure numbers is explained."""
    paper_dir = Path(paper_dir)
    entries = {e["id"]: e for e in (json.loads(p.read_text()) for p in sorted((paper_dir / "index").glob("*.json")))}
    order = list(dict.fromkeys([exp for exp, _ in (figures or {}).values()] + sorted(entries)))
    lines = ["# Regenerated figures and tables", "",
             "Made by `make paper` (or each experiment alone with the command shown). Ids name the tracked",
             "datasets, perception maps and error maps each result used."]
    locks = sorted(p.name for p in paper_dir.glob("*.lock.yaml"))
    if locks:
        lines.append("Every input of this folder, with its config hash and code version: "
                     + ", ".join(f"[{name}]({name})" for name in locks) + ".")
    lines += ["", *numbering_note(paper_dir, figures)]
    for exp in order:
        e = entries.get(exp)
        if e is None:
            continue
        lines += [f"## {e['id']} — {e['title']}", "", f"- command: `{e['command']}`",
                  f"- reproduces: {e.get('paper', '–')}"]
        for k, v in sorted(e.get("inputs", {}).items()):
            lines.append(f"- {k}: `{v}`")
        lines.append(f"- results cache: `{e.get('cache', '–')}`")
        lines.append("")
        for it in e["items"]:
            files = ", ".join(f"[{f}]({f})" for f in it["files"])
            label = f" ({it['reproduces']})" if it.get("reproduces") else ""
            lines.append(f"- {it['kind']}{label}: {it['caption']} — {files}")
        lines.append("")
    lines += other_files(paper_dir, set(re.findall(r"\]\(([^)]+)\)", "\n".join(lines))))
    return write_atomic(paper_dir / "index.md", "\n".join(lines))


# The files of a paper folder that no experiment's entry lists: (pattern, what it is), the first match wins
OTHER_FILES = [
    ("*.lock.yaml", "the lock: every input of the run that wrote this folder, with its config hash and code version"),
    ("*.profile.md", "the profile of the last run of the config of the same name (`make paper`, `make multi`) that "
                     "started a job: wall and CPU time per stage and job, and the phases each job timed"),
    ("*.profile.json", "that run's walls per job, as JSON (the next run starts the longest jobs first)"),
    ("tab_learned.md", "learned end-to-end policies against the paper's architecture: success, collision and stall "
                       "rates (make learned's comparison; copied from `outputs/learned/learned-<id>/`, "
                       "the lock's `learned.comparison`; the line under it says what its pixel-attack rows show, "
                       "and why make run's budget separates no agent: docs/learned.md, \"The κ curve\")"),
    ("fig_learned_switching_set.png", "the imitated policy's switching set over the arena (e_b · π(h(p)); black: "
                                      "its own set K), from make learned's comparison (docs/learned.md)"),
    ("tab_certified_*.md", "the certified error map of one perception map (make paper: the occluded map on the band "
                           "behind the obstacle): its certified ε̄ against c - r, Theorem 1's hypothesis, the sampled "
                           "and attacked errors beside it (copied from `outputs/certified/<map>-<id>/`; docs/certify.md)"),
    ("fig_certified_*.png", "the same certified error map drawn beside the sampled one (docs/certify.md)"),
    ("tab_bracket_*.md", "the closed loop's bracket for one tuning or field (make multi): certified ε_lo and falsified ε_hi per controller, "
                         "and with a certified error map (make paper: the band's) the start cells certified, falsified "
                         "(a signal within the map's ε̄ breaks the loop) and undecided with the map's own bound "
                         "(copied from `outputs/bracket/bracket-<id>/`; docs/bracket.md)"),
    ("fig_bracket_*.png", "the same bracket drawn over the start cells; hatched: certified (top) and falsified (bottom) "
                          "with the map's ε̄ (docs/bracket.md)"),
    ("index/*.json", "an experiment's index entry: the record this page is written from"),
    (".*.experiments.json", "the experiments stage's stamp: the command its last run started with (the stage is not "
                            "started again while it and every file of its entries are unchanged)"),
]


def other_files(paper_dir: Path, linked: set[str]) -> list[str]:
    """Lines linking every file under `paper_dir` that is not in `linked` (index.md and half-written temporaries
    aside), each with what it is (:data:`OTHER_FILES`)."""
    names = sorted(str(p.relative_to(paper_dir)) for p in Path(paper_dir).rglob("*") if p.is_file())
    rest = [n for n in names if n not in linked and n != "index.md" and not fnmatch(Path(n).name, ".*.tmp")]
    if not rest:
        return []
    unknown = ("no entry of this index lists it: left by an earlier run or another command (or written by an "
               "experiment still running, not recorded yet)")
    groups: dict[str, list[str]] = {w: [] for _, w in OTHER_FILES} | {unknown: []}  # in OTHER_FILES' order
    for n in rest:
        groups[next((w for pattern, w in OTHER_FILES if fnmatch(n, pattern)), unknown)].append(n)
    groups = {w: files for w, files in groups.items() if files}
    lines = ["## Other files in this folder", ""]
    lines += [f"- {what} — " + ", ".join(f"[{n}]({n})" for n in files) for what, files in groups.items()]
    return [*lines, ""]


def numbering_note(paper_dir: Path, figures: dict = FIGURES) -> list[str]:
    """A line naming each figure number below the highest in `paper_dir` that the folder lacks (the numbers are one
    sequence over `make paper`, `make generalisation` and `make multi`), with the configs that make it."""
    present = {int(m.group(1)) for p in Path(paper_dir).glob("fig*") if (m := re.match(r"fig(\d+)_", p.name))}
    missing = [(stem, exp) for stem, (exp, _) in (figures or {}).items()
               if (m := re.match(r"fig(\d+)_", stem)) and int(m.group(1)) not in present
               and present and int(m.group(1)) < max(present)]
    if not missing:
        return []
    runs = _configs_running()
    parts = [f"{stem} (experiment `{exp}`, made by " + (" or ".join(runs.get(exp, [])) or "no config of conf/")
             + ")" for stem, exp in missing]
    return ["Figure numbers are one sequence over `make paper`, `make generalisation` and `make multi` "
            "(`pipeline/experiments/report.py`, FIGURES); not in this folder: " + "; ".join(parts) + ".", ""]


def _configs_running() -> dict[str, list[str]]:
    """experiment id -> the commands of the paper configs (conf/*.yaml with an `experiments` list) that run it:
    `make <target>` where the Makefile has one, else `python -m pipeline.paper --config-name <config>`."""
    import yaml

    makefile = REPO_ROOT / "Makefile"
    targets = dict((c, t) for t, c in re.findall(r"^([\w-]+):[^\n]*\n\t\$\(PY\) -m pipeline\.paper --config-name (\w+)",
                                                 makefile.read_text() if makefile.is_file() else "", re.M))
    out: dict[str, list[str]] = {}
    for path in sorted(CONF_DIR.glob("*.yaml")):
        exps = (yaml.safe_load(path.read_text()) or {}).get("experiments")
        if isinstance(exps, list):
            name = path.stem
            cmd = f"`make {targets.get(name, 'paper')}`" if name in targets or name == "paper" else \
                f"`python -m pipeline.paper --config-name {name}`"
            for exp in exps:
                out.setdefault(str(exp), []).append(cmd)
    return out


def draw_frame(ax, scene: Scene, arena, diamond: bool = True):
    draw_scene(ax, scene, arena, diamond=diamond)
    ax.set_xlim(*arena[0])
    ax.set_ylim(*arena[1])
    ax.set_aspect("equal")
