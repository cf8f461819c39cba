"""`make docs-check` (issue 46): which documented map ids the current code still gives, and which tables do not say
how they were measured. Every id here is computed by the checker's own function, never copied from the docs."""

from __future__ import annotations

import json

import yaml

from pipeline.docs_check import NOT_A_MAP, expected_ids, main, references, report, tables
from pipeline.repo import CONF_DIR


def _map_id(expected: dict, name: str, config: str = "paper") -> str:
    return next(id_ for id_, kind in expected[name].items() if kind == f"{config}'s map")


def _page(tmp_path, current: str, stale: str):
    """A page quoting a current id, a stale one and a bracket output; a table with provenance, one without, and a
    table-like block inside a code fence."""
    md = tmp_path / "page.md"
    md.write_text("\n".join([
        "# Results",
        "",
        f"Measured 2026-12-03 with `python -m pipeline.certify maps={current}`:",
        "",
        "| map | MAE |",
        "|---|---|",
        f"| `{current}` | 0.07 |",
        "",
        f"An older map, `{stale}`, gave the numbers below (`outputs/bracket/bracket-0123abcdef`).",
        "",
        "| map | MAE |",
        "|---|---|",
        "| old | 0.27 |",
        "",
        "```",
        "| not | a table |",
        "|---|---|",
        "```",
    ]) + "\n")
    return md


def test_a_current_id_a_stale_one_and_a_table_without_provenance_are_told_apart(tmp_path):
    expected = expected_ids(["paper"])
    current_id = _map_id(expected, "clean_keypoint")
    stale_id = "0123456789" if current_id != "0123456789" else "9876543210"
    md = _page(tmp_path, f"clean_keypoint-{current_id}", f"clean_keypoint-{stale_id}")

    refs = {(r.line, f"{r.name}-{r.id}"): r for r in references([md], expected, root=tmp_path)}
    assert set(refs) == {(3, f"clean_keypoint-{current_id}"), (7, f"clean_keypoint-{current_id}"),
                         (9, f"clean_keypoint-{stale_id}"), (9, "bracket-0123abcdef")}
    assert refs[3, f"clean_keypoint-{current_id}"].status == "current"
    assert refs[9, f"clean_keypoint-{stale_id}"].status == "stale"
    assert f"clean_keypoint-{current_id}" in refs[9, f"clean_keypoint-{stale_id}"].current
    assert (refs[9, "bracket-0123abcdef"].status, refs[9, "bracket-0123abcdef"].current) == ("-", NOT_A_MAP)
    assert all(r.file == "page.md" for r in refs.values())

    found = {t.line: t.missing for t in tables([md], root=tmp_path)}
    assert found == {5: (), 11: ("date", "command")}  # the fenced block is no table

    text = report([md], expected, root=tmp_path)
    assert "1 of 3 documented ids are stale" in text.splitlines()[-1]
    assert "1 of 2 tables have no provenance" in text.splitlines()[-1]
    assert "| page.md | 11 | date and command |" in text


def test_every_map_make_paper_and_make_multi_train_gets_the_id_the_paper_job_computes():
    from pipeline import tracking
    from pipeline.config import compose
    from pipeline.identity import map_identity
    from pipeline.lineage import map_recipe, train_dataset_id

    expected = expected_ids()
    for config in ("paper", "multi"):
        cfg = yaml.safe_load((CONF_DIR / f"{config}.yaml").read_text())
        for name in cfg["maps"]:
            recipe, extra = map_recipe(name)
            train = [*((cfg.get("args") or {}).get("train") or [])]
            tcfg = compose("train", [f"data={recipe}", *extra, *train])
            assert map_identity(tracking.to_plain_lenient(tcfg), *train_dataset_id(tcfg)) == \
                (name, _map_id(expected, name, config))


def test_a_built_maps_error_map_id_counts_as_current(tmp_path):
    """Where the map is built, the error map the paper job would compute for it is current too (the error map's
    folder has the map's name)."""
    from pipeline.config import compose
    from pipeline.lineage import errormap_identity

    paths = [f"paths.root_dir={tmp_path}"]
    map_id = _map_id(expected_ids(["paper"], paths), "clean_keypoint")
    manifest = {"name": "clean_keypoint", "id": map_id, "scene": {"target": [40.0, 0.0]},
                "arena": [[-50.0, 50.0], [-30.0, 30.0]], "model": {"outputs": "position"}}
    folder = tmp_path / "outputs" / "models" / f"clean_keypoint-{map_id}"
    folder.mkdir(parents=True)
    (folder / "manifest.json").write_text(json.dumps(manifest))
    assert compose("paper", paths).paths.models_dir == str(folder.parent)

    expected = expected_ids(["paper"], paths)
    em_id = errormap_identity(compose("errormap", [f"maps={folder.name}", *paths]), manifest)[1]
    assert expected["clean_keypoint"][em_id] == "paper's error map"
    md = tmp_path / "em.md"
    md.write_text(f"error map `clean_keypoint-{em_id}`\n")
    assert [r.status for r in references([md], expected, root=tmp_path)] == ["current"]


def test_the_command_prints_the_report_and_exits_0(tmp_path, capsys):
    md = _page(tmp_path, "clean_keypoint-0123456789", "occluded_keypoint-0123456789")
    assert main([str(md), "--configs", "paper"]) == 0
    out = capsys.readouterr().out
    assert "## Documented ids" in out and "## Tables without provenance" in out
    assert out.splitlines()[-1].startswith("3 of 3 documented ids are stale")
