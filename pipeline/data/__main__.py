"""`python -m pipeline.data [data=<recipe>] [overrides]` (multirun: `-m data=clean,occluded`)."""

from __future__ import annotations

import re
import sys

from omegaconf import DictConfig

from pipeline.cli import CONF_DIR, stage_main

_GROUPS = {"data": "dataset recipe", "scene": "scene", "render": "render config"}


def check_group_options(argv: list[str]) -> str | None:
    """One-line message for an unknown option of the stage's config groups (Hydra's own is multi-line)."""
    for arg in argv:
        m = re.fullmatch(r"(?:\+{1,2})?(data|scene|render)=(.*)", arg)
        if not m or "(" in m.group(2):  # sweep functions (glob, choice, ...) are left to Hydra
            continue
        group, values = m.groups()
        known = sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))
        for v in values.split(","):
            if v.strip() not in known:
                return f"{group}: unknown {_GROUPS[group]} {v.strip()!r} (known: {', '.join(known)})"
    return None


@stage_main("data")
def main(cfg: DictConfig) -> None:
    from pipeline.data.stage import run

    run(cfg)


if __name__ == "__main__":
    msg = check_group_options(sys.argv[1:])
    if msg:
        print(f"error: {msg}", file=sys.stderr)
        sys.exit(2)
    main()
