"""`make bench`: every area's benchmark in one run, printed as one table.

Each area exposes `pipeline.<area>.bench.bench(quick=False) -> list[dict]` (rows with section, case, value,
unit, note). Absolute numbers depend on the machine and its load; ratios are measured in the same run.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time

AREAS = ("sim", "data", "train", "errormap", "experiments")


def collect(areas=AREAS, quick: bool = False) -> list[dict]:
    rows = []
    for area in areas:
        try:
            mod = importlib.import_module(f"pipeline.{area}.bench")
        except ModuleNotFoundError as err:
            if err.name and err.name.startswith(f"pipeline.{area}"):
                continue  # that area has no benchmark
            raise
        t0 = time.perf_counter()
        area_rows = mod.bench(quick=quick)
        print(f"[bench] {area}: {len(area_rows)} rows in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        rows += area_rows
    return rows


def format_table(rows: list[dict]) -> str:
    head = ("section", "case", "value", "unit", "note")
    cells = [[str(r.get("section", "")), str(r.get("case", "")), _fmt(r.get("value")), str(r.get("unit", "")),
              str(r.get("note", ""))] for r in rows]
    widths = [max(len(h), *(len(c[i]) for c in cells)) if cells else len(h) for i, h in enumerate(head)]
    line = lambda c: "| " + " | ".join(x.ljust(w) for x, w in zip(c, widths)) + " |"  # noqa: E731
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(head), sep, *(line(c) for c in cells)])


def _fmt(v) -> str:
    if isinstance(v, int | float):
        return f"{v:,.3g}" if abs(v) < 1000 else f"{v:,.0f}"
    return str(v)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("areas", nargs="*", default=list(AREAS), help=f"subset of {AREAS}")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (seconds), for smoke tests")
    args = ap.parse_args(argv)
    unknown = set(args.areas) - set(AREAS)
    if unknown:
        print(f"error: unknown bench area(s) {sorted(unknown)}; choose from {AREAS}", file=sys.stderr)
        return 2
    print(f"# bench on {os.cpu_count()} CPU cores (GLIBC_TUNABLES={os.environ.get('GLIBC_TUNABLES', '')})")
    print(format_table(collect(args.areas, quick=args.quick)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
