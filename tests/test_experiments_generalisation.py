"""Experiment perception_generalisation (issue 11, item 4): the table's numbers against stub maps with a known
error, the follower column against a perfect map and a map that always answers the obstacle centre, one-line
errors, the cache key follows the map ids, and map names such as `clean_paper` resolve by id."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from shared import run_cli  # tests/shared.py

from pipeline import tracking
from pipeline.cli import REPO_ROOT, compose
from pipeline.config import build
from pipeline.errors import ConfigError
from pipeline.render import Camera

OFFSET = np.array([3.0, 4.0])  # world units: a Euclidean error of exactly 5 units


class RecordingCamera(Camera):
    """The real camera, remembering for each batch it rendered the leaders' true positions and the cloud
    opacity over them (so that a stub map can answer with a known error)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.batches: dict[int, tuple] = {}

    def render(self, leader, follower=None, occlusion=None, rng=None, *, clouds=None, out=None, return_info=False):
        res = super().render(leader, follower, occlusion, rng, clouds=clouds, out=out, return_info=True)
        # keep the images alive: their id is the key
        self.batches[id(res.images)] = (res.images, np.asarray(leader, float).reshape(-1, 2), res.leader_alpha)
        return res if return_info else res.images


class StubMap:
    """`answer(true positions, leader alpha) -> estimates`: a map with a known error."""

    def __init__(self, name, camera, answer, id_):
        self.name, self.id, self._camera, self.answer = name, id_, camera, answer
        self.px_per_unit = camera.scale
        self.manifest = {}
        self.seen: list[tuple[np.ndarray, np.ndarray]] = []

    def camera(self):
        return self._camera

    def predict(self, images):
        _, true, alpha = self._camera.batches[id(images)]
        self.seen.append((true, alpha))
        return self.answer(true, alpha)


def _cfg(tmp_path, *extra):
    return compose("experiments", ["experiment=perception_generalisation", f"paths.paper_dir={tmp_path / 'paper'}",
                                   f"paths.outputs_dir={tmp_path / 'out'}", "publish=true", *extra])


@pytest.fixture
def stubs(monkeypatch, tmp_path):
    """Maps under the names of the bundle: exact, offset by (3, 4) units, clouds-blind (exact where the leader
    is visible, the obstacle centre (0, 0) where clouds hide it: leader_alpha >= 0.8), always the obstacle
    centre. Context.perception_map answers them instead of trained maps."""
    from pipeline.experiments.context import Context

    cfg = compose("experiments")
    render = {k: v for k, v in tracking.to_plain(cfg.render).items() if k != "_target_"}
    cam = RecordingCamera(build(cfg.scene, "scene"), **render)
    maps = {
        "clean": StubMap("exact", cam, lambda p, a: p.copy(), "aaaaaaaaaa"),
        "occluded": StubMap("offset", cam, lambda p, a: p + OFFSET, "bbbbbbbbbb"),
        "authors": StubMap("blind", cam, lambda p, a: np.where((a >= 0.8)[:, None], 0.0, p), "cccccccccc"),
        "clean_paper": StubMap("centre", cam, lambda p, a: np.zeros_like(p), "dddddddddd"),
    }
    monkeypatch.setattr(Context, "perception_map", lambda self, kind: maps[kind])
    # the Context resolves a map's folder (its id, its manifest) without loading it: the stubs' folders
    folders = tmp_path / "stub_models"
    for m in maps.values():
        (folders / f"{m.name}-{m.id}").mkdir(parents=True)
        (folders / f"{m.name}-{m.id}" / "manifest.json").write_text(json.dumps(m.manifest))
    monkeypatch.setattr(Context, "map_folder", lambda self, kind="clean": folders / f"{maps[kind].name}-{maps[kind].id}")
    monkeypatch.setattr(Context, "camera", lambda self, kind="clean": maps[kind].camera())
    return maps


SMALL = ["experiment.n_positions=300", "experiment.n_near_target=40", "experiment.n_agents=4",
         "experiment.levels=[none,authors,heavy]"]


def test_table_numbers_match_the_stub_maps_known_errors(stubs, tmp_path):
    from pipeline.experiments.stage import run

    # the follower columns are test_follower_success_perfect_map_all_obstacle_centre_none's: a 2 s horizon here
    out = run(_cfg(tmp_path, *SMALL, "experiment.maps=[clean,occluded,authors]", "sim.horizon=2.0"))
    table = pd.read_csv(tmp_path / "paper" / "tab_perception_generalisation.csv")
    # one row per map x level, in the bundle's order
    assert list(zip(table["map"], table["level"])) == [(m, lv) for m in ("clean", "occluded", "authors")
                                                       for lv in ("none", "authors", "heavy")]
    ppu = stubs["clean"].px_per_unit
    rows = table.set_index(["map", "level"])
    for level in ("none", "authors", "heavy"):
        exact, offset = rows.loc[("clean", level)], rows.loc[("occluded", level)]
        assert exact.mae_px == 0 and exact.p95_px == 0 and exact.near_target_p95_px == 0
        assert offset.mae_px == pytest.approx(3.5 * ppu)  # per-coordinate MAE of (3, 4)
        assert offset.p95_px == pytest.approx(5 * ppu) and offset.near_target_p95_px == pytest.approx(5 * ppu)
    # clouds-blind: exact without clouds; on hidden frames its error is the distance of the leader to (0, 0)
    assert rows.loc[("authors", "none"), "mae_px"] == 0 and rows.loc[("authors", "none"), "hidden_share"] == 0
    assert np.isnan(rows.loc[("authors", "none"), "hidden_mae_px"])
    n = int(out["results"].tables["perception"]["n"].iloc[0])
    seen = [(p, a) for p, a in stubs["authors"].seen if len(p) == n]  # the uniform batches, in level order
    assert len(seen) == 3
    for (true, alpha), level in zip(seen, ("none", "authors", "heavy")):
        hidden = alpha >= 0.8
        assert rows.loc[("authors", level), "hidden_share"] == pytest.approx(hidden.mean())
        if hidden.any():
            assert rows.loc[("authors", level), "hidden_mae_px"] == pytest.approx(np.abs(true[hidden]).mean() * ppu)
            assert rows.loc[("authors", level), "mae_px"] == pytest.approx(np.abs(true[hidden]).sum() * ppu / (2 * n))
        # every map saw the same positions at every level
        np.testing.assert_array_equal(true, seen[0][0])
    assert rows.loc[("authors", "heavy"), "hidden_share"] > 0.05  # heavy clouds hide some leaders
    assert rows.loc[("authors", "heavy"), "mae_px"] > rows.loc[("authors", "authors"), "mae_px"] >= 0
    # the table's numbers are the cached results', written as CSV / Markdown / LaTeX, and the figure is fig13
    res = out["results"].tables["summary"]
    assert res["mae_px"].to_numpy() == pytest.approx(table["mae_px"].to_numpy())
    paper = tmp_path / "paper"
    assert (paper / "tab_perception_generalisation.tex").read_text().startswith("\\begin{table}")
    assert "| clean | none |" in (paper / "tab_perception_generalisation.md").read_text()
    assert (paper / "fig13_perception_generalisation.png").stat().st_size > 1000
    index = (paper / "index.md").read_text()
    assert "## perception_generalisation" in index and "fig13_perception_generalisation.png" in index


def test_follower_success_perfect_map_all_obstacle_centre_none(stubs, tmp_path):
    from pipeline.experiments.stage import run

    out = run(_cfg(tmp_path, *SMALL, "experiment.maps=[clean,clean_paper]", "experiment.levels=[none,heavy]",
                   "experiment.n_positions=50", "experiment.n_near_target=0"))
    rows = out["results"].tables["summary"].set_index(["map", "level"])
    for level in ("none", "heavy"):
        assert rows.loc[("clean", level), "follower_n"] == 4
        assert rows.loc[("clean", level), "follower_success_rate"] == 1.0
        assert rows.loc[("clean", level), "follower_collision_rate"] == 0.0
        assert rows.loc[("clean_paper", level), "follower_success_rate"] == 0.0
        assert rows.loc[("clean_paper", level), "follower_success_practical"] == 0.0
    raw = pd.read_csv(tmp_path / "paper" / "metrics_perception_generalisation.csv")
    assert len(raw) == 2 * 2 * 4 and set(raw["level"]) == {"none", "heavy"}


def test_cache_key_follows_the_map_ids(stubs, tmp_path):
    from pipeline import tracking
    from pipeline.experiments.checks import build_scenario
    from pipeline.experiments.context import Context
    from pipeline.experiments.stage import cache_key

    cfg = _cfg(tmp_path, "experiment.maps=[clean,occluded]")
    scen = build_scenario(cfg)

    def key():
        return tracking.content_id(cache_key(cfg, scen, Context(cfg)))

    first = key()
    assert cache_key(cfg, scen, Context(cfg))["maps"] == {"clean": "aaaaaaaaaa", "occluded": "bbbbbbbbbb"}
    stubs["authors"].id = "eeeeeeeeee"  # a map the experiment does not use
    assert key() == first
    stubs["occluded"].id = "ffffffffff"
    assert key() != first


def test_bad_input_is_one_line_exit_2(tmp_path):
    base = [sys.executable, "-m", "pipeline.experiments", "experiment=perception_generalisation",
            f"paths.paper_dir={tmp_path / 'p'}", f"paths.outputs_dir={tmp_path / 'o'}",
            f"paths.models_dir={tmp_path / 'm'}", f"hydra.run.dir={tmp_path / 'run'}"]
    cases = [("+experiment.n_position=5", "error: experiment.n_position: unknown key"),
             ("experiment.levels=[none,cloudy]", "error: experiment.levels: unknown occlusion level 'cloudy'"),
             ("experiment.maps=[clean,mine]", "error: experiment.maps: 'mine' is not in the composed `maps` node"),
             ("experiment.maps=[clean_paper]", "run `python -m pipeline.train data=clean model=paper`")]
    for i, (override, message) in enumerate(cases):  # the first in a fresh interpreter, the others in this process
        proc = subprocess.run([*base, override], cwd=REPO_ROOT, capture_output=True, text=True, timeout=300) if i == 0 \
            else run_cli(*base[2:], override)
        assert proc.returncode == 2, (override, proc.stderr[-2000:])
        assert len(proc.stderr.strip().splitlines()) == 1 and message in proc.stderr, (override, proc.stderr)


def test_scenario_rejects_bad_parameters():
    from pipeline.experiments.generalisation.maps import PerceptionGeneralisation

    with pytest.raises(ConfigError, match="experiment.levels"):
        PerceptionGeneralisation(id="g", title="g", levels=["none", "none"])
    with pytest.raises(ConfigError, match="experiment.hidden_alpha"):
        PerceptionGeneralisation(id="g", title="g", hidden_alpha=1.5)
    with pytest.raises(TypeError):
        PerceptionGeneralisation(id="g", title="g", n_position=5)  # no **kwargs: a typo is not a default


def test_map_names_resolve_by_the_id_their_train_config_makes(tmp_path):
    from pipeline.identity import map_identity
    from pipeline.lineage import expected_map_id, map_command, map_recipe
    from pipeline.paper import check

    assert map_recipe("authors") == ("authors", []) and map_recipe("clean_paper") == ("clean", ["model=paper"])
    assert map_recipe("closed_loop_paper") == ("closed_loop", ["model=paper"]) and map_recipe("clean_papr") is None
    assert map_command("clean_paper") == "python -m pipeline.train data=clean model=paper"
    from pipeline.lineage import train_dataset_id

    tcfg = compose("train", ["data=clean", "model=paper"])
    assert map_identity(tracking.to_plain_lenient(tcfg), *train_dataset_id(tcfg)) == \
        ("clean_paper", expected_map_id("clean_paper"))
    assert expected_map_id("clean_paper") != expected_map_id("clean")
    assert expected_map_id("clean_default") is None  # model=default makes `clean`, not `clean_default`
    check(compose("paper_full"))
    check(compose("paper_generalisation"))
    with pytest.raises(ConfigError, match="maps: unknown map 'clean_papr'"):
        check(compose("paper", ["maps=[clean,clean_papr]"]))
    with pytest.raises(ConfigError, match="trained on datasets not among"):
        check(compose("paper", ["maps=[clean,authors]"]))
