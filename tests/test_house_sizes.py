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
