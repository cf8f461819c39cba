"""`make paper`: the DAG data -> train -> errormap -> experiments, each stage as its own Hydra job.

Every stage skips work whose tracked output is up to date (same config, inputs and code), so a second
`make paper` with nothing changed only re-draws the figures and tables under `outputs/paper/`.
"""

from __future__ import annotations

import subprocess
import sys
import time

from pipeline import tracking
from pipeline.cli import REPO_ROOT, stage_main
from pipeline.errors import ConfigError, PipelineError


def _path_overrides() -> list[str]:
    """`paths.*` overrides given to the paper job are passed on to every stage."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return [o for o in HydraConfig.get().overrides.task if o.lstrip("+").startswith("paths.")]
    except Exception:  # noqa: BLE001 - not under @hydra.main
        return []


def stage_commands(cfg) -> list[tuple[str, list[str]]]:
    args = tracking.to_plain(cfg.args) or {}
    paths = _path_overrides()
    datasets = list(cfg.datasets)
    maps = list(cfg.maps)
    if not datasets:
        raise ConfigError("datasets", "needs at least one recipe")
    missing = set(maps) - set(datasets)
    if missing:
        raise ConfigError("maps", f"{sorted(missing)} are not among the datasets {datasets}")
    cmds = [("data", ["-m", f"data={','.join(datasets)}", *paths, *args.get("data", [])])]
    if maps:
        cmds.append(("train", ["-m", f"data={','.join(maps)}", *paths, *args.get("train", [])]))
    if cfg.errormaps:
        cmds.append(("errormap", [f"maps=[{','.join(cfg.errormaps)}]", *paths, *args.get("errormap", [])]))
    if cfg.experiments:
        cmds.append(("experiments", ["-m", f"experiment={','.join(cfg.experiments)}", *paths,
                                     *args.get("experiments", [])]))
    return cmds


def run(cfg) -> dict:
    t0 = time.perf_counter()
    timings = {}
    for stage, argv in stage_commands(cfg):
        cmd = [sys.executable, "-m", f"pipeline.{stage}", *argv]
        print(f"\n[paper] === {stage}: {' '.join(cmd[1:])}", flush=True)
        ts = time.perf_counter()
        proc = subprocess.run(cmd, cwd=REPO_ROOT, check=False)
        timings[stage] = time.perf_counter() - ts
        if proc.returncode != 0:
            msg = f"stage {stage} failed (exit {proc.returncode}); fix it and re-run `make paper` (done stages are re-used)"
            if cfg.get("stop_on_error", True):
                raise PipelineError(msg)
            print(f"[paper] {msg}", flush=True)
    total = time.perf_counter() - t0
    line = ", ".join(f"{k} {v:.0f} s" for k, v in timings.items())
    print(f"\n[paper] done in {total / 60:.1f} min ({line}); see {cfg.paths.paper_dir}/index.md")
    return {"timings": timings, "total": total}


@stage_main("paper")
def main(cfg):
    return run(cfg)


if __name__ == "__main__":
    sys.exit(main())
