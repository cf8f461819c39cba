"""The house stays carryable (issue 27; DEVELOPERS.md): no module of `pipeline` over 400 lines, no function over 80."""

from __future__ import annotations

import ast

from pipeline.cli import REPO_ROOT

MODULE_LINES, FUNCTION_LINES = 400, 80


def _modules():
    return sorted((REPO_ROOT / "pipeline").rglob("*.py"))


def test_no_module_over_400_lines():
    long = {str(p.relative_to(REPO_ROOT)): n for p in _modules() if (n := len(p.read_text().splitlines())) > MODULE_LINES}
    assert not long, f"modules over {MODULE_LINES} lines: {long}"


def test_no_function_over_80_lines():
    long = {}
    for p in _modules():
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > FUNCTION_LINES:
                    long[f"{p.relative_to(REPO_ROOT)}:{node.lineno} {node.name}"] = n
    assert not long, f"functions over {FUNCTION_LINES} lines: {long}"


def test_the_config_layer_is_at_most_600_lines():
    """Issue 27: the config framework (schema, signatures, config, preflight) was about 1,000 lines; signatures.py is
    gone (a torch class takes a typed spec) and the other three stay at most 600 together."""
    layer = {name: len((REPO_ROOT / "pipeline" / name).read_text().splitlines())
             for name in ("schema.py", "config.py", "preflight.py")}
    assert not (REPO_ROOT / "pipeline" / "signatures.py").exists()
    assert sum(layer.values()) <= 600, f"the config layer is {sum(layer.values())} lines: {layer}"


IN_FUNCTION_IMPORTS = 10  # issue 47: 51 at filing


def in_function_pipeline_imports(source: str) -> list[tuple[int, str]]:
    """`(line, text)` of each `import pipeline...` / `from pipeline... import` statement inside a function body."""
    lines, found = source.splitlines(), []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            for sub in ast.walk(node):
                names = [a.name for a in sub.names] if isinstance(sub, ast.Import) else \
                    [sub.module or ""] if isinstance(sub, ast.ImportFrom) and sub.level == 0 else []
                if any(n == "pipeline" or n.startswith("pipeline.") for n in names):
                    found.append((sub.lineno, lines[sub.lineno - 1]))
    return sorted(set(found))


def test_in_function_pipeline_imports_are_few_and_each_says_why():
    """Issue 47: a dependency hidden in a function is one a reader of the imports does not see; at most 10 in
    `pipeline/`, each with a comment on its line saying why it waits (torch, matplotlib: not in the preflight)."""
    found = {f"{p.relative_to(REPO_ROOT)}:{n}": text for p in _modules()
             for n, text in in_function_pipeline_imports(p.read_text())}
    assert len(found) <= IN_FUNCTION_IMPORTS, sorted(found)
    bare = [k for k, text in found.items() if "#" not in text]
    assert not bare, f"in-function imports without a comment saying why: {bare}"


def test_the_import_count_sees_nested_and_multi_line_imports():
    src = "import pipeline.a\ndef f():\n    if x:\n        from pipeline.b import (  # why\n            c)\n" \
          "    import os\n    from . import d\n    import pipeline\n"
    assert [n for n, _ in in_function_pipeline_imports(src)] == [4, 8]


def test_the_longest_first_modules_exist_and_the_order_keeps_every_test_once(request):
    """tests/conftest.py's `LONGEST_FIRST` names test modules that exist (a renamed one would silently fall back to
    file order and its long test could run last again), and its reordering moves modules, never drops or repeats a
    test: this session's collection holds each collected test id once, the listed modules first."""
    import conftest  # tests/conftest.py

    names = {p.name for p in (REPO_ROOT / "tests").glob("test_*.py")}
    assert set(conftest.LONGEST_FIRST) <= names, sorted(set(conftest.LONGEST_FIRST) - names)
    items = request.session.items
    ids = [i.nodeid for i in items]
    assert len(ids) == len(set(ids))
    ranks = [conftest.LONGEST_FIRST.index(i.path.name) if i.path.name in conftest.LONGEST_FIRST else
             len(conftest.LONGEST_FIRST) for i in items]
    assert ranks == sorted(ranks)
