"""What the reader sees is true (issue 46): index.md links every file of the paper folder and explains a gap in the
figure numbers; fig14's caption speaks of a gated series only when one is drawn; fig8 keeps equal curves apart
and shows the strict and the practical success criterion."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from shared import index_links  # tests/shared.py

from pipeline.experiments.report import Outputs, publish, write_index


def _entry(exp: str, files: list[str]) -> dict:
    return {"id": exp, "title": exp, "paper": "–", "command": f"python -m pipeline.experiments experiment={exp}",
            "inputs": {}, "cache": f"../experiments/{exp}-0123456789",
            "items": [{"kind": "figure", "files": files, "caption": "c"}]}


def _fill(paper: Path, stems: dict[str, str]) -> None:
    """A paper folder as `make paper` leaves it: experiments' entries with their files (`stems`: experiment ->
    figure stem), the lock, the profile, the files copied from the learned and bracket stages, the stamp."""
    for exp, stem in stems.items():
        files = [f"{stem}.png", f"{stem}.pdf", f"tab_{exp}.csv", f"metrics_{exp}.csv"]
        for f in files:
            (paper / f).parent.mkdir(parents=True, exist_ok=True)
            (paper / f).write_text("x")
        publish(paper, _entry(exp, files))
    for f in ("paper.lock.yaml", "paper.profile.md", "paper.profile.json", "tab_learned.md",
              "fig_learned_switching_set.png", "tab_bracket_paper.md", "fig_bracket_paper.png",
              ".paper.lock.experiments.json", "notes.txt"):
        (paper / f).write_text("x")


def test_index_links_every_file_of_the_paper_folder(tmp_path):
    paper = tmp_path / "paper"
    _fill(paper, {"sample_and_hold": "fig12_sample_and_hold", "camera_attack": "fig14_camera_attack"})
    index = write_index(paper)
    links = index_links(index)
    files = {str(p.relative_to(paper)) for p in paper.rglob("*") if p.is_file()} - {"index.md"}
    assert files <= links, f"not linked from index.md: {sorted(files - links)}"
    assert all((paper / link).is_file() for link in links), "a link to nothing"
    text = index.read_text()
    assert "profile" in text and "learned" in text and "left by an earlier run" in text  # notes.txt: said what it is
    line = next(s for s in text.splitlines() if "[paper.profile.md]" in s)
    assert "wall and CPU time" in line


def test_index_explains_a_gap_in_the_figure_numbers(tmp_path):
    paper = tmp_path / "paper"
    _fill(paper, {"sample_and_hold": "fig12_sample_and_hold", "camera_attack": "fig14_camera_attack"})
    text = write_index(paper).read_text()
    note = next(s for s in text.splitlines() if "not in this folder" in s)
    assert "fig13_perception_generalisation" in note and "make generalisation" in note
    assert "fig9_" in note  # every number below the highest that the folder lacks
    assert "fig17_" not in note  # make multi's, after the highest here: not a gap
    whole = tmp_path / "whole"
    _fill(whole, {"perception_closeness": "fig1_perception_closeness", "sensitive_set": "fig2_sensitive_set"})
    assert "not in this folder" not in write_index(whole).read_text()  # contiguous: nothing to explain


# ---------------------------------------------------------------------------------------- fig14's caption
class _Kept(Outputs):
    """Outputs that also keep each figure drawn (its lines are checked against its caption)."""

    def __init__(self, *a):
        super().__init__(*a)
        self.figs = []

    def figure(self, fig, stem, caption):
        self.figs.append(fig)
        return super().figure(fig, stem, caption)


def _attack_summary(gated: bool) -> pd.DataFrame:
    rows = []
    for budget in (0.0, 1.0):
        for ctrl, g in [("hybrid", False), ("smooth", False), ("cbf", False)] + ([("hybrid", True)] if gated else []):
            rows.append({"budget": budget, "attack": f"pixel κ={budget:g}", "controller": ctrl, "gated": g, "n": 4,
                         **{f"{k}_{s}": v for k in ("success", "stalled", "collision")
                            for s, v in (("rate", 0.5), ("lo", 0.2), ("hi", 0.8))},
                         "timed_out": 0.0, "induced_along_near_K": 0.1, "induced_norm_near_K": 0.1,
                         "induced_along_start": 0.1, "induced_norm_start": 0.1, "induced_norm_run": 0.1,
                         "flag_rate": 0.2, "flag_rate_near_K": 0.1, "gated_share": 0.3 if g else 0.0,
                         "frames_near_K": 10})
    return pd.DataFrame(rows)


@pytest.mark.parametrize("gated", [False, True])
def test_fig14_caption_names_a_gated_series_only_when_it_is_drawn(tmp_path, gated):
    from pipeline.experiments.attacks.figures import draw_camera_attack

    res = SimpleNamespace(tables={"summary": _attack_summary(gated)}, info={"gate": 0.25, "notes": []}, arrays={})
    out = _Kept(tmp_path, "camera_attack")
    draw_camera_attack(SimpleNamespace(id="camera_attack"), None, res, out)
    caption = next(it["caption"] for it in out.items if it["kind"] == "figure")
    series = [(c.get_label(), c.lines[0].get_linestyle()) for ax in out.figs[0].axes[:2] for c in ax.containers]
    assert {label for label, _ in series} >= {"hybrid", "smooth", "cbf"}
    dashed = [label for label, ls in series if ls == "--"]
    assert bool(dashed) == gated, dashed
    assert ("dashed: the loop gated" in caption) == gated, caption
    if not gated:
        assert "ungated loops only" in caption and "experiment.gated" in caption
        table = next(it["caption"] for it in out.items if it["kind"] == "table")
        assert "no gated loop ran" in table
    else:
        assert all("(gated)" in label for label in dashed)


# ---------------------------------------------------------------------------------------- fig8
def _sweep() -> pd.DataFrame:
    """smooth and CBF equal everywhere; the hybrid strict 0 but practical 1 at ε = 1 (the equilibrium moved by ε)."""
    rows = []
    for dist in ("adversarial", "alternating"):
        for eps in (0.0, 0.5, 1.0):
            for ctrl in ("hybrid", "smooth", "cbf"):
                strict = 1.0 if eps == 0 or (ctrl == "hybrid" and eps < 1) else 0.0
                practical = 1.0 if eps == 0 or ctrl == "hybrid" else 0.0
                rows.append({"scene": "default", "disturbance": dist, "eps": eps, "controller": ctrl, "n": 10,
                             "success_rate": strict, "success_lo": strict * 0.7, "success_hi": min(1, strict + 0.3),
                             "practical_success_rate": practical, "practical_lo": practical * 0.7,
                             "practical_hi": min(1, practical + 0.3), "collision_rate": 0.0, "stalled": 0.0,
                             "mean_jumps": 0.0})
    return pd.DataFrame(rows)


def test_fig8_keeps_equal_curves_apart_and_shows_both_criteria(tmp_path):
    from pipeline.experiments.paper.figures import draw_robustness_sweep

    out = _Kept(tmp_path, "robustness_sweep")
    draw_robustness_sweep(None, SimpleNamespace(delta=1.0), SimpleNamespace(tables={"sweep": _sweep()}), out)
    fig, caption = out.figs[0], out.items[0]["caption"]
    axes = [ax for ax in fig.axes if ax.get_lines()]
    assert len(axes) == 4  # strict and practical, per disturbance
    titles = " ".join(ax.get_title() for ax in axes)
    assert "strict" in titles and "practical" in titles and "δ + ε" in titles
    assert "strict" in caption and "practical" in caption and "δ + ε" in caption
    for ax in axes:
        lines = {ln.get_label(): ln for ln in ax.get_lines()}
        assert set(lines) == {"hybrid", "smooth", "cbf"}
        styles = {(ln.get_marker(), str(ln.get_linestyle())) for ln in lines.values()}
        assert len(styles) == 3, styles  # one marker and line style per controller
        xy = [np.column_stack(ln.get_data()) for ln in lines.values()]
        assert not any(np.allclose(a, b) for i, a in enumerate(xy) for b in xy[i + 1:])  # none hides another
    practical = next(ax for ax in axes if "practical" in ax.get_title() and "adversarial" in ax.get_title())
    hybrid = next(ln for ln in practical.get_lines() if ln.get_label() == "hybrid")
    assert hybrid.get_ydata()[-1] == 1.0  # practical success of the hybrid at ε = 1, where the strict one is 0
    json.dumps(out.items)  # what index.md records
