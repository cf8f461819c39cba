"""Stage jobs of `make paper` run side by side (issue 30): `workers` processes at a time, each on its share of the
cores, each job's wall and CPU time measured (`pipeline.paper_profile` writes them into the run's profile).

On a 2-core CPU two single-threaded jobs do more than one job on two threads: the maps are small convolutions and
the closed loops are mostly Python, so a second thread adds little to one job (`make bench`: the rows "side by
side" of the sections train and infer; docs/speed.md).
With one worker a job's output streams to the terminal as before; with several, each job writes
`<log_dir>/<label>.log` and the orchestrator prints one line when a job starts and one when it ends (and the
log's last lines when it fails). A job may wait for others of its pool (`after`: their labels; the bracket waits
for its certified error map, the learned comparison for its policies). Jobs start by their critical path: a job's
own wall (the previous run's profile) plus the longest chain of jobs waiting for it, so a short job that a long
one waits for goes first, and otherwise the longest first (without a profile: the jobs others wait for, then the
jobs that waited, then the order given).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.errors import PipelineError
from pipeline.profiling import ENV as PROFILE_ENV
from pipeline.repo import REPO_ROOT

TAIL_LINES = 25  # lines of a failed job's log printed with its failure


@dataclass(frozen=True)
class Job:
    """`python -m pipeline.<stage> <argv>` (or `python -m <module> <argv>`), called `label` in the logs and the
    profile; started once the jobs of its pool labelled in `after` have succeeded (labels not in the pool: done
    before it)."""

    stage: str
    argv: list[str]
    label: str
    module: str | None = None
    after: tuple[str, ...] = ()

    @property
    def command(self) -> list[str]:
        return [sys.executable, "-m", self.module or f"pipeline.{self.stage}", *self.argv]


@dataclass
class Done:
    job: Job
    rc: int
    wall: float
    cpu: float
    log: Path | None = None
    phases: dict = field(default_factory=dict)


def threads_per_job(workers: int) -> int:
    """The cores each of `workers` side-by-side jobs gets (at least one)."""
    return max(1, (os.cpu_count() or 1) // max(1, workers))


def _env(threads: int | None, profile: Path | None) -> dict:
    env = dict(os.environ)
    if threads is not None:  # torch, OpenMP and BLAS read these when they start
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    if profile is not None:
        env[PROFILE_ENV] = str(profile)
    return env


POLL = 0.05  # seconds between looks at the running jobs


def _reap(procs: dict) -> tuple[int, int, float] | None:
    """Wait for one of `procs` (pid -> ...) to end: (pid, exit code, CPU seconds of that child); None when none is
    left. Only these pids are waited for: other children of the process (a test runner's) are left alone."""
    while procs:
        for pid in list(procs):
            try:
                done, status, usage = os.wait4(pid, os.WNOHANG)
            except ChildProcessError:
                return pid, -1, 0.0
            if done:
                return pid, os.waitstatus_to_exitcode(status), usage.ru_utime + usage.ru_stime
        time.sleep(POLL)
    return None


def critical_paths(jobs: list[Job], order: dict[str, float]) -> dict[str, float]:
    """Per label: its expected seconds (`order`; unknown: 0) plus the longest chain of jobs waiting for it."""
    waiting = {j.label: [k for k in jobs if j.label in k.after] for j in jobs}
    memo: dict[str, float] = {}

    def path(label: str, seen: frozenset) -> float:
        if label in seen:
            raise ValueError(f"jobs wait for each other in a circle: {' -> '.join([*seen, label])}")
        if label not in memo:
            memo[label] = order.get(label, 0.0) + max((path(k.label, seen | {label}) for k in waiting[label]),
                                                       default=0.0)
        return memo[label]

    return {j.label: path(j.label, frozenset()) for j in jobs}


def _ready(queue: deque, finished: dict[str, int], labels: set[str]) -> Job | None:
    """The first queued job whose pool dependencies have all finished (removed from the queue), or None."""
    for job in queue:
        if all(finished.get(a) == 0 for a in job.after if a in labels):
            queue.remove(job)
            return job
    return None


def _skip_failed(queue: deque, finished: dict[str, int], labels: set[str], tag: str) -> list[Done]:
    """Take out of the queue every job one of whose pool dependencies failed (or was skipped), transitively; each
    said in one line, returned as done with exit code -1."""
    skipped = []
    while failed := [j for j in queue if any(finished.get(a, 0) != 0 for a in j.after if a in labels)]:
        for job in failed:
            queue.remove(job)
            finished[job.label] = -1
            skipped.append(Done(job, -1, 0.0, 0.0))
            print(f"[{tag}] SKIPPED {job.label}: {', '.join(a for a in job.after if finished.get(a, 0) != 0)} failed",
                  flush=True)
    return skipped


def run_jobs(jobs: list[Job], *, workers: int, tag: str, stop: bool, log_dir: Path | None = None,
             profile: Path | None = None, order: dict[str, float] | None = None) -> list[Done]:
    """Run `jobs`, `workers` at a time, each once its `after` jobs have succeeded, by critical path
    (:func:`critical_paths` over `order`: label -> expected seconds). A failure prints its log's tail and raises
    `PipelineError` (`stop`: the other running jobs are ended first) or is returned, and the jobs waiting for it
    are skipped (said in one line each, exit code -1). Ctrl-C reaches every job (each says so in one line) and
    ends the run with exit code 130."""
    order = order or {}
    if len({j.label for j in jobs}) < len(jobs):
        raise ValueError(f"jobs of one pool share a label: {sorted(j.label for j in jobs)}")
    priority = critical_paths(jobs, order)
    waited_for = {a for j in jobs for a in j.after}
    # by critical path; on a tie (a fresh clone has no profile: every path 0) the jobs others wait for first, then
    # those that waited, then the given order
    queue = deque(sorted(jobs, key=lambda j: (-priority[j.label], j.label not in waited_for, not j.after)))
    labels, finished = {j.label for j in jobs}, {}  # label -> exit code
    parallel = workers > 1 and len(jobs) > 1
    if parallel and log_dir is None:
        raise ValueError("jobs side by side write logs: log_dir is needed")
    threads = threads_per_job(min(workers, len(jobs))) if parallel else None
    env = _env(threads, profile)
    if parallel:
        log_dir.mkdir(parents=True, exist_ok=True)
        print(f"[{tag}] {len(jobs)} jobs, {min(workers, len(jobs))} at a time on {threads} thread(s) each; "
              f"logs in {log_dir}", flush=True)
    running: dict[int, tuple[Job, subprocess.Popen, float, Path | None]] = {}
    done: list[Done] = []
    try:
        while queue or running:
            done += _skip_failed(queue, finished, labels, tag)
            while queue and len(running) < (workers if parallel else 1):
                job = _ready(queue, finished, labels)
                if job is None:  # every queued job waits for a running one
                    if not running:
                        raise PipelineError(f"jobs {[j.label for j in queue]} wait for jobs that never start")
                    break
                cmd = job.command
                log = log_dir / f"{job.label.replace(' ', '_')}.log" if parallel else None
                if parallel:
                    print(f"[{tag}] start {job.label}", flush=True)
                    out = open(log, "w", encoding="utf-8")  # noqa: SIM115 - closed when the job ends
                else:
                    print(f"\n[{tag}] === {job.label}: {' '.join(cmd[1:])}", flush=True)
                    out = None
                proc = subprocess.Popen(cmd, cwd=REPO_ROOT, env=env, stdout=out, stderr=subprocess.STDOUT if out else None)
                if out is not None:
                    out.close()
                running[proc.pid] = (job, proc, time.perf_counter(), log)
            reaped = _reap(running)
            if reaped is None or reaped[0] not in running:
                continue
            pid, rc, cpu = reaped
            job, proc, t0, log = running.pop(pid)
            proc.returncode = rc  # reaped here: Popen must not wait for it again
            d = Done(job, rc, time.perf_counter() - t0, cpu, log)
            done.append(d)
            finished[job.label] = rc
            if parallel:
                print(f"[{tag}] {'done' if rc == 0 else 'FAILED'} {job.label}: {d.wall:.0f} s wall, "
                      f"{d.cpu:.0f} s CPU ({len(done)}/{len(jobs)})", flush=True)
            if rc == 130:
                raise KeyboardInterrupt
            if rc != 0:
                if log is not None:
                    tail = log.read_text(encoding="utf-8", errors="replace").splitlines()[-TAIL_LINES:]
                    print("\n".join(f"    {line}" for line in tail), flush=True)
                msg = (f"stage {job.stage} failed for {job.label} (exit {rc}); fix it and re-run `make {tag}` "
                       "(done stages are re-used)")
                if stop:
                    _end(running)
                    raise PipelineError(msg)
                print(f"[{tag}] {msg}", flush=True)
    except KeyboardInterrupt:  # the jobs got the Ctrl-C too and said so in their one line: say nothing more
        _end(running)
        raise SystemExit(130) from None
    return done


def _end(running: dict) -> None:
    for _job, proc, _t0, _log in running.values():
        proc.terminate()
    for _job, proc, _t0, _log in running.values():
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    running.clear()
