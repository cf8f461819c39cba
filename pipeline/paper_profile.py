"""The profile of a `make paper` run (issue 30): by stage and by job, wall and CPU time and what dominates.

`Runner.stage` runs a stage's jobs side by side (:mod:`pipeline.jobs`) and keeps each job's wall and CPU time;
the jobs record their own phases (:mod:`pipeline.profiling`: rendering and inference inside the closed loops,
computing and drawing a bundle, fitting a map, ...). `write_profile` joins both into `profile.md` (a table a
reader can quote: every later speed claim names its row) and `profile.json` (the walls, which the next run uses
to start the longest jobs first) in the paper's folder.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import time
from pathlib import Path

import pandas as pd

from pipeline.experiments.report import markdown_table
from pipeline.jobs import Done, Job, run_jobs
from pipeline.profiling import read_phases

NESTED = ("render", "inference")  # phases timed inside another (the closed loop's frames inside `compute`)
COLUMNS = ("stage", "job", "wall s", "CPU s", "CPU / wall", "start-up and rest", "fit", "uncertainty head",
           "evaluate", "train samples", "error fields", "compute", "render", "inference", "draw", "cached")  # others follow


class Runner:
    """Runs the stages of one `make paper` (or `make multi`) and profiles them."""

    def __init__(self, cfg, timings: dict[str, float], stop: bool, tag: str = "paper"):
        self.paper_dir = Path(cfg.paths.paper_dir)
        self.name = Path(str(cfg.lock)).stem.removesuffix(".lock")  # paper, multi, ...
        self.workers = int(cfg.get("workers") or os.cpu_count() or 1)
        self.timings, self.stop, self.tag = timings, stop, tag
        self.log_dir = _log_dir(self.paper_dir)
        self.phases_file = self.log_dir / "phases.jsonl"
        self.done: list[tuple[str, Done]] = []
        self._held: list | None = None  # the stages held for one pool (together)
        self.closed = False  # every stage ran: a stage called again only reads and publishes
        self.said: set[str] = set()  # the stages reported up to date (said once per run)
        self.made_by: dict[str, str] = {}  # output folder name -> label of the job of this run that makes it

    def _order(self) -> dict[str, float]:
        try:
            return json.loads((self.paper_dir / f"{self.name}.profile.json").read_text())["walls"]
        except (OSError, ValueError, KeyError):
            return {}

    def stage(self, stage: str, jobs: list[Job], then=None) -> bool:
        """Run `jobs` (`self.workers` at a time); the stage's elapsed wall goes to `timings[stage]`; `then()` after,
        if every job succeeded. Inside :meth:`together` the jobs are held for its pool (False: not run yet); once
        `closed`, nothing runs (False)."""
        if self.closed:
            return False
        if self._held is not None:
            self._held.append((stage, jobs, then))
            return False
        return self._run([(stage, jobs, then)])

    @contextlib.contextmanager
    def together(self):
        """The stages started inside the block run as one pool when it ends (their jobs side by side, the longest
        first): stages none of which reads another's output. Their wall goes to `timings["a + b"]`."""
        self._held = []
        try:
            yield
            held = self._held
        finally:
            self._held = None
        if held:
            self._run(held)

    def _run(self, stages) -> bool:
        self.log_dir.mkdir(parents=True, exist_ok=True)  # the jobs append their phases there, alone or side by side
        t0 = time.perf_counter()
        jobs = [self._waiting(j) for _, js, _ in stages for j in js]
        of = {j.label: stage for stage, js, _ in stages for j in js}
        done = run_jobs(jobs, workers=self.workers, tag=self.tag, stop=self.stop, log_dir=self.log_dir,
                        profile=self.phases_file, order=self._order())
        self.said.update(stage for stage, _, _ in stages)  # ran: not "up to date, not started" when called again
        key = " + ".join(dict.fromkeys(stage for stage, _, _ in stages))
        self.timings[key] = self.timings.get(key, 0.0) + time.perf_counter() - t0
        self.done += [(of[d.job.label], d) for d in done]
        ok = {stage: all(d.rc == 0 for d in done if of[d.job.label] == stage) for stage, _, _ in stages}
        for stage, _, then in stages:
            if then is not None and ok[stage]:
                then()
        return all(ok.values())

    def _waiting(self, job: Job) -> Job:
        """`job`, waiting also for the jobs of its pool that make an output its command line names (`made_by`);
        a job of another pool, or a folder already built, is not waited for (:func:`pipeline.jobs.run_jobs`)."""
        named = {t for arg in job.argv for t in re.split(r"[=\[\],/\s]", arg)}  # whole folder names, not parts
        makers = [label for name, label in self.made_by.items() if label != job.label and name in named]
        return dataclasses.replace(job, after=tuple(dict.fromkeys((*job.after, *makers))))

    def table(self) -> pd.DataFrame:
        phases = read_phases(self.phases_file)
        rows = []
        for stage, d in self.done:
            rec = phases.get(d.job.label, {})
            ph = rec.get("phases", {})
            row = {"stage": stage, "job": d.job.label, "wall s": d.wall, "CPU s": d.cpu,
                   "CPU / wall": d.cpu / d.wall if d.wall else float("nan")}
            row.update({k: v for k, v in ph.items()})
            row["start-up and rest"] = d.wall - sum(v for k, v in ph.items() if k not in NESTED)
            if "cached" in rec:
                row["cached"] = rec["cached"]
            rows.append(row)
        df = pd.DataFrame(rows)
        return df[[c for c in COLUMNS if c in df] + [c for c in df if c not in COLUMNS]]

    def write_profile(self, total: float) -> Path | None:
        """`<name>.profile.md` and `.json` in the paper's folder (nothing when no job ran)."""
        if not self.done:
            return None
        table = self.table()
        self.paper_dir.mkdir(parents=True, exist_ok=True)
        stages = ", ".join(f"{k} {v:.0f} s" for k, v in self.timings.items())
        md = [f"# Profile of `make {self.name}`", "",
              f"{total / 60:.1f} min in all ({stages}); {self.workers} job(s) side by side on "
              f"{os.cpu_count()} cores. Seconds per job: wall and CPU (all its threads), and the phases it "
              "timed (render and inference are inside compute: the closed loop's camera frames); "
              "`start-up and rest` is the wall outside the timed phases (imports, config, loading, writing).", "",
              markdown_table(table.round(1)), "",
              f"Job logs: `{self.log_dir}`.", ""]
        path = self.paper_dir / f"{self.name}.profile.md"
        path.write_text("\n".join(md))
        walls = {**self._order(), **{d.job.label: round(d.wall, 1) for _s, d in self.done}}
        (self.paper_dir / f"{self.name}.profile.json").write_text(
            json.dumps({"total_s": round(total, 1), "stages": self.timings, "walls": walls}, indent=2) + "\n")
        print(f"[{self.tag}] profile: {path}", flush=True)
        return path


def _log_dir(paper_dir: Path) -> Path:
    """The paper job's Hydra run folder when there is one (its logs beside its config), else beside the paper."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return Path(HydraConfig.get().runtime.output_dir) / "jobs"
    except Exception:  # noqa: BLE001 - not under @hydra.main
        return paper_dir.parent / "runs" / "jobs"
