"""Which documented numbers still hold (issue 46): `python -m pipeline.docs_check`, `make docs-check`.

README.md and docs/*.md quote tracked outputs by `name-id` (`occluded_keypoint-feb737ba11`): the map a table was
measured with. When the code or a config changes, the id the current code gives a name changes, and a reader cannot
tell which tables still hold. This report lists every quoted `<name>-<10 hex>`, and for each map name that
`make paper` or `make multi` trains (conf/paper.yaml, conf/multi.yaml: `maps`) the id the current code and config
give it, computed as the paper job does before it runs a stage (:func:`pipeline.lineage.expected_map_id` with the
config's `args.train`; nothing is trained, torch is not imported). Where that map is built here, the ids of its
error map and certified error map under the same config count as current too (they hash the map's manifest). A
second section lists the markdown tables whose 6 lines above name no measurement date (`2026-12-03`) or no command
(`python -m ...` or `make ...`, in backticks or on a line of its own): tables that do not say how to regenerate them.
It is a report: the exit status is 0 whatever it finds.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

from pipeline import tracking
from pipeline.config import compose
from pipeline.errors import PipelineError
from pipeline.identity import certify_id
from pipeline.lineage import errormap_identity, expected_map_id
from pipeline.repo import REPO_ROOT

CONFIGS = ("paper", "multi")  # the configs of `make paper` and `make multi`
REFERENCE = re.compile(r"\b([a-z][a-z0-9_]*)-([0-9a-f]{10})\b")
TABLE_SEP = re.compile(r"^\s*\|?\s*:?-{3,}:?\s*(\|\s*:?-{3,}:?\s*)*\|?\s*$")
DATE = re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b")
COMMAND = re.compile(r"`(?:python -m |make )[^`]*`|^\s*(?:python -m |make )\S", re.M)
ABOVE = 6  # lines above a table that may say how it was measured
NOT_A_MAP = "not a make paper map"


@dataclass(frozen=True)
class Reference:
    """A `name-id` quoted in a markdown file, and what the current code gives that name."""

    file: str
    line: int
    name: str
    id: str
    current: str  # the current map's `name-id` (with what the documented id matched), or NOT_A_MAP
    status: str  # current, stale, or "-" (a name no make paper/multi config trains)


@dataclass(frozen=True)
class Table:
    """A markdown table and what its lines above lack (`date`, `command`)."""

    file: str
    line: int
    header: str
    missing: tuple[str, ...]


def documents(root: Path = REPO_ROOT) -> list[Path]:
    """README.md and docs/*.md."""
    return [p for p in [root / "README.md", *sorted((root / "docs").glob("*.md"))] if p.is_file()]


# ------------------------------------------------------------------------------------- the current ids
def _derived_ids(cfg, name: str, map_id: str, overrides: list[str]) -> dict[str, str]:
    """{id: kind} of the error map and certified error map `cfg` (a paper config; `overrides` join each stage's,
    as the paper job passes its own on) makes of the map `name-map_id`, where that map is built (their ids hash its
    manifest); empty when it is not."""
    folder = Path(cfg.paths.models_dir) / f"{name}-{map_id}"
    if not (folder / tracking.MANIFEST).is_file():
        return {}
    out = {}
    try:
        m = tracking.read_manifest(folder)
        if name in cfg.errormaps:
            em = compose("errormap", [f"maps={folder.name}", *overrides, *cfg.args.errormap])
            out[errormap_identity(em, m)[1]] = "error map"
        if name in cfg.certify:
            c = compose("certify", [f"maps={folder.name}", *overrides, *cfg.args.certify])
            s = tracking.to_plain({k: c[k] for k in c.keys() if k not in ("paths", "hydra")})
            out[certify_id(s, m["id"], m["scene"], m["arena"])] = "certified error map"
    except (PipelineError, KeyError, ValueError) as err:
        print(f"[docs_check] {folder.name}: its error-map ids not computed ({err})", file=sys.stderr)
    return out


def expected_ids(configs: Iterable[str] = CONFIGS, overrides: Iterable[str] = ()) -> dict[str, dict[str, str]]:
    """{map name: {id: what it is}} of every map the paper configs `configs` train, under the current code and
    config: the map's id as `python -m pipeline.paper --config-name <config>` computes it before training (`paper's
    map`), and its error map's and certified error map's where it is built (`paper's error map`). `overrides`
    (`paths.*`, `debug=<level>`) join the paper config and each stage's, as the paper job passes its own on."""
    overrides = list(overrides)
    out: dict[str, dict[str, str]] = {}
    for config in configs:
        cfg = compose(config, overrides)
        for name in cfg.maps:
            map_id = expected_map_id(str(name), [*overrides, *cfg.args.train])
            if map_id is None:
                continue
            out.setdefault(str(name), {})[map_id] = f"{config}'s map"
            for id_, kind in _derived_ids(cfg, str(name), map_id, overrides).items():
                out[str(name)].setdefault(id_, f"{config}'s {kind}")
    return out


# ------------------------------------------------------------------------------------------ the scan
def _label(path: Path, root: Path) -> str:
    try:
        return str(path.relative_to(root))
    except ValueError:
        return str(path)


def references(paths: Iterable[Path], expected: Mapping[str, Mapping[str, str]], root: Path = REPO_ROOT) \
        -> list[Reference]:
    """Every `name-id` of the files (once per line), classified against `expected` (:func:`expected_ids`)."""
    out = []
    for path in paths:
        for no, text in enumerate(Path(path).read_text().splitlines(), 1):
            for name, id_ in dict.fromkeys(REFERENCE.findall(text)):
                ids = expected.get(name)
                if ids is None:
                    current, status = NOT_A_MAP, "-"
                elif id_ in ids:
                    current, status = f"{name}-{id_} ({ids[id_]})", "current"
                else:
                    maps = [f"{name}-{i} ({k})" for i, k in ids.items() if k.endswith("'s map")]
                    current, status = ", ".join(maps), "stale"
                out.append(Reference(_label(Path(path), root), no, name, id_, current, status))
    return out


def _missing(above: list[str]) -> tuple[str, ...]:
    text = "\n".join(above)
    return tuple(k for k, rx in (("date", DATE), ("command", COMMAND)) if not rx.search(text))


def tables(paths: Iterable[Path], root: Path = REPO_ROOT) -> list[Table]:
    """Every markdown table of the files (outside code fences) and what its `ABOVE` lines above lack."""
    out = []
    for path in paths:
        lines = Path(path).read_text().splitlines()
        fenced, inside = False, False
        for i, text in enumerate(lines):
            if text.lstrip().startswith("```"):
                fenced = not fenced
            starts = (not fenced and not inside and text.lstrip().startswith("|") and i + 1 < len(lines)
                      and TABLE_SEP.match(lines[i + 1]) is not None)
            if starts:
                out.append(Table(_label(Path(path), root), i + 1, text.strip()[:60],
                                 _missing(lines[max(0, i - ABOVE):i])))
            inside = not fenced and text.lstrip().startswith("|") and (inside or starts)
    return out


# ---------------------------------------------------------------------------------------- the report
def markdown(rows: list[dict]) -> str:
    """A markdown table of `rows` (dicts with the same keys); `(none)` when there are none."""
    if not rows:
        return "(none)\n"
    cols = list(rows[0])
    cell = lambda v: str(v).replace("|", "\\|")  # noqa: E731
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    return "\n".join([*lines, *("| " + " | ".join(cell(r[c]) for c in cols) + " |" for r in rows)]) + "\n"


def summary(refs: list[Reference], tabs: list[Table]) -> str:
    """The report's last line: how many checked ids are stale, and how many tables lack provenance."""
    checked = [r for r in refs if r.status != "-"]
    stale = sum(r.status == "stale" for r in checked)
    bare = sum(len(t.missing) == 2 for t in tabs)
    half = sum(len(t.missing) == 1 for t in tabs)
    return (f"{stale} of {len(checked)} documented ids are stale (ids of make paper/multi maps; "
            f"{len(refs) - len(checked)} other ids not checked); {bare} of {len(tabs)} tables have no provenance "
            f"(neither a date nor a command in the {ABOVE} lines above), {half} more lack one of them")


def report(paths: Iterable[Path], expected: Mapping[str, Mapping[str, str]], root: Path = REPO_ROOT) -> str:
    """The whole report: documented ids, tables without provenance, the summary line."""
    paths = list(paths)
    refs, tabs = references(paths, expected, root), tables(paths, root)
    ids = [{"file": r.file, "line": r.line, "documented id": f"{r.name}-{r.id}", "current code gives": r.current,
            "status": r.status} for r in refs]
    bare = [{"file": t.file, "line": t.line, "lacks": " and ".join(t.missing), "table": t.header}
            for t in tabs if t.missing]
    return (f"## Documented ids\n\n{markdown(ids)}\n## Tables without provenance\n\n"
            f"Their {ABOVE} lines above name no measurement date or no `python -m`/`make` command.\n\n"
            f"{markdown(bare)}\n{summary(refs, tabs)}\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.docs_check", description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="*", type=Path, help="markdown files (default: README.md and docs/*.md)")
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS),
                        help=f"paper configs whose maps are checked (default: {' '.join(CONFIGS)})")
    args = parser.parse_args(argv)
    print(report(args.files or documents(), expected_ids(args.configs)), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
