"""Every row of README.md's results table names the command that produced its numbers.

The README's results ("## Results ..." section) once said "make paper, default config" over rows that came from
other runs (100-start bundles, flat maps of an earlier code), while `make run` writes different numbers. Each row's
first cell must now name its command, in backticks: `make <target>` for a target of the Makefile, or
`python -m pipeline.<module> ...` for a module that exists (a config of its own: `--config-name ...`).
"""

from __future__ import annotations

import importlib.util
import re

import pytest

from pipeline.cli import REPO_ROOT

README = REPO_ROOT / "README.md"
SECTION = re.compile(r"^## Results\b.*$", re.M)
CELL_SEP = re.compile(r"(?<!\\)\|")  # `\|` inside a cell is text
CODE = re.compile(r"`([^`]+)`")


def make_targets() -> set[str]:
    return set(re.findall(r"^([A-Za-z_][\w-]*):", (REPO_ROOT / "Makefile").read_text(), re.M))


def _module_exists(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        return False


def results_rows(text: str) -> list[tuple[int, str]]:
    """(line number, first cell) of each body row of the first table under the "## Results" heading."""
    heading = SECTION.search(text)
    assert heading, "README.md: no '## Results' section"
    rows, in_table = [], False
    start = text[:heading.start()].count("\n") + 1
    for offset, line in enumerate(text[heading.end():].splitlines()):
        if line.startswith("## "):
            break
        if line.startswith("|"):
            in_table = True
            cells = CELL_SEP.split(line.strip())[1:-1]
            if cells and not re.fullmatch(r"\s*:?-+:?\s*", cells[0]):
                rows.append((start + offset, cells[0].strip()))
        elif in_table:
            break
    return rows[1:]  # the header row


def commands(cell: str, targets: set[str] | None = None) -> list[str]:
    """The commands quoted in a cell that really exist: `make <target>`, `python -m pipeline.<module> ...`."""
    targets = make_targets() if targets is None else targets
    found = []
    for code in CODE.findall(cell):
        words = code.split()
        if len(words) >= 2 and words[0] == "make" and words[1] in targets:
            found.append(code)
        elif (len(words) >= 3 and words[:2] == ["python", "-m"] and words[2].startswith("pipeline")
              and _module_exists(words[2])):
            found.append(code)
    return found


def test_every_results_row_names_the_command_behind_its_numbers():
    rows = results_rows(README.read_text())
    assert len(rows) > 20, rows
    targets = make_targets()
    missing = [f"README.md:{line}: {cell[:80]}" for line, cell in rows if not commands(cell, targets)]
    assert not missing, "results rows naming no `make <target>` / `python -m pipeline.<module>`:\n" + "\n".join(missing)


SYNTHETIC = """# x

## Results on some machine

| what | value |
|---|---|
| robustness sweep (`make paper`, `tab_robustness_sweep.md`) | hybrid 100% |
| pixel attack near K (100 starts) | smooth 0% |
| certify (`python -m pipeline.certify maps=clean`) | sound |
| a typo'd target (`make papr`) | 1 |
| a module that is not there (`python -m pipeline.nosuchstage`) | 2 |
| an escaped bar in the first cell (\\|p - p_T\\| <= 1, `make run`) | 3 |

after the table: | not a row (`make paper`) |

## Next section

| what | value |
|---|---|
| not in the results (no command) | 4 |
"""


def test_the_parser_reads_the_results_table_and_rejects_rows_without_a_real_command():
    rows = results_rows(SYNTHETIC)
    assert [cell.split(" (")[0] for _, cell in rows] == [
        "robustness sweep", "pixel attack near K", "certify", "a typo'd target", "a module that is not there",
        "an escaped bar in the first cell"]
    named = {cell.split(" (")[0]: commands(cell, {"paper", "run"}) for _, cell in rows}
    assert named["robustness sweep"] == ["make paper"]
    assert named["certify"] == ["python -m pipeline.certify maps=clean"]
    assert named["an escaped bar in the first cell"] == ["make run"]
    for bad in ("pixel attack near K", "a typo'd target", "a module that is not there"):
        assert named[bad] == [], bad


@pytest.mark.parametrize("cell", ["`experiment=hysteresis_margin`", "`model=paper trainer=paper`",
                                  "make paper (no backticks)", "`make`", "`python -m os`"])
def test_an_override_or_an_unquoted_command_is_not_a_command(cell):
    assert commands(cell, {"paper"}) == []
