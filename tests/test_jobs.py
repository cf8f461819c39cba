"""Jobs side by side (`pipeline.jobs`, issue 30) and the profile of a run (`pipeline.paper_profile`).

The jobs are small Python modules written to a temporary folder (on PYTHONPATH): they report what they see
(their thread budget, each other) through files, so every property is checked without timing anything.
"""

from __future__ import annotations

import json
import os
import textwrap
from types import SimpleNamespace

import pytest

from pipeline import jobs as jobs_mod
from pipeline.errors import PipelineError
from pipeline.jobs import Job, run_jobs, threads_per_job
from pipeline.paper_profile import Runner
from pipeline.profiling import read_phases

CHILD = textwrap.dedent('''
    import os, sys, time
    from pathlib import Path
    from pipeline.profiling import phase, record
    out, me, other, rc = Path(sys.argv[1]), sys.argv[2], sys.argv[3], int(sys.argv[4])
    with phase("compute"):
        (out / f"{me}.threads").write_text(os.environ.get("OMP_NUM_THREADS", "unset"))
        with open(out / "order.txt", "a") as fh:
            fh.write(me + "\\n")
        if other != "-":  # wait for the other job's marker: only jobs that run side by side both finish
            (out / f"{me}.started").write_text("")
            t0 = time.time()
            while not (out / f"{other}.started").exists():
                if time.time() - t0 > 60:
                    sys.exit(5)
                time.sleep(0.02)
    print(f"{me}: the last line of my log")
    record(f"job {me}", cached=False)
    sys.exit(rc)
''')


@pytest.fixture
def child(tmp_path, monkeypatch):
    pkg = tmp_path / "mods"
    pkg.mkdir()
    (pkg / "fake_stage.py").write_text(CHILD)
    monkeypatch.setenv("PYTHONPATH", f"{pkg}")
    out = tmp_path / "out"
    out.mkdir()

    def job(me, other="-", rc=0, after=()):
        return Job("fake", [str(out), me, other, str(rc)], f"job {me}", module="fake_stage",
                   after=tuple(f"job {a}" for a in after))

    return job, out


def test_two_workers_run_side_by_side_on_their_share_of_the_cores(child, tmp_path):
    job, out = child
    done = run_jobs([job("a", "b"), job("b", "a")], workers=2, tag="t", stop=True, log_dir=tmp_path / "logs")
    assert sorted(d.job.label for d in done) == ["job a", "job b"] and all(d.rc == 0 for d in done)
    assert (out / "a.threads").read_text() == str(threads_per_job(2))
    assert all(d.log is not None and "the last line of my log" in d.log.read_text() for d in done)
    assert all(d.wall > 0 and d.cpu > 0 for d in done)


def test_one_worker_keeps_every_core_and_runs_the_longest_job_first(child, tmp_path):
    job, out = child
    run_jobs([job("short"), job("long")], workers=1, tag="t", stop=True, log_dir=tmp_path / "logs",
             order={"job long": 100.0, "job short": 1.0})
    assert (out / "order.txt").read_text().split() == ["long", "short"]
    # one job at a time: the process's own setting (none, or what the caller's environment says)
    assert (out / "long.threads").read_text() == os.environ.get("OMP_NUM_THREADS", "unset")


def test_a_failed_job_raises_with_its_label_and_its_log_tail(child, tmp_path, capsys):
    job, _ = child
    with pytest.raises(PipelineError, match="job bad"):
        run_jobs([job("good"), job("bad", rc=3)], workers=2, tag="t", stop=True, log_dir=tmp_path / "logs")
    assert "bad: the last line of my log" in capsys.readouterr().out


def test_without_stop_a_failure_is_returned_and_the_others_finish(child, tmp_path):
    job, _ = child
    done = run_jobs([job("bad", rc=3), job("good")], workers=2, tag="t", stop=False, log_dir=tmp_path / "logs")
    assert {d.job.label: d.rc for d in done} == {"job bad": 3, "job good": 0}


def test_a_job_waits_for_the_jobs_it_reads_and_short_chains_to_long_jobs_go_first(child, tmp_path):
    """The bracket waits for its certified map, the learned comparison for its policies: one pool, each started
    once what it reads is done; by critical path, the short job a long one waits for starts first."""
    job, out = child
    order = {"job long": 100.0, "job certify": 10.0, "job bracket": 120.0, "job other": 50.0}
    run_jobs([job("long"), job("bracket", after=["certify"]), job("certify"), job("other")], workers=1, tag="t",
             stop=True, log_dir=tmp_path / "logs", order=order)
    assert (out / "order.txt").read_text().split() == ["certify", "bracket", "long", "other"]
    (out / "order.txt").unlink()
    run_jobs([job("long"), job("bracket", after=["certify"]), job("certify"), job("other")], workers=1, tag="t",
             stop=True, log_dir=tmp_path / "logs")  # no profile (a fresh clone): the chain first, then as given
    assert (out / "order.txt").read_text().split() == ["certify", "bracket", "long", "other"]
    paths = jobs_mod.critical_paths([job("a", after=["b"]), job("b", after=["c"]), job("c")],
                                    {"job a": 1.0, "job b": 2.0, "job c": 4.0})
    assert paths == {"job a": 1.0, "job b": 3.0, "job c": 7.0}
    with pytest.raises(ValueError, match="circle"):
        jobs_mod.critical_paths([job("a", after=["b"]), job("b", after=["a"])], {})


def test_a_job_whose_input_failed_is_skipped_and_one_outside_the_pool_counts_as_done(child, tmp_path, capsys):
    job, out = child
    done = run_jobs([job("bad", rc=3), job("reader", after=["bad"]), job("next", after=["reader"]),
                     job("free", after=["elsewhere"])], workers=2, tag="t", stop=False, log_dir=tmp_path / "logs")
    assert {d.job.label: d.rc for d in done} == {"job bad": 3, "job reader": -1, "job next": -1, "job free": 0}
    assert not (out / "reader.threads").exists()  # never started
    assert "SKIPPED job reader: job bad failed" in capsys.readouterr().out


def _runner(tmp_path, monkeypatch, timings: dict, stop: bool) -> Runner:
    """A runner of two workers writing its logs and profile under `tmp_path`."""
    monkeypatch.setattr("pipeline.paper_profile._log_dir", lambda paper_dir: tmp_path / "logs")
    cfg = SimpleNamespace(paths=SimpleNamespace(paper_dir=str(tmp_path / "paper")), lock="paper.lock.yaml",
                          get=lambda key, default=None: {"workers": 2}.get(key, default))
    return Runner(cfg, timings, stop=stop)


def test_the_profile_joins_walls_and_the_phases_each_job_recorded(child, tmp_path, monkeypatch):
    job, _ = child
    timings: dict[str, float] = {}
    runner = _runner(tmp_path, monkeypatch, timings, stop=True)
    assert runner.stage("experiments", [job("a", "b"), job("b", "a")])
    phases = read_phases(runner.phases_file)
    assert set(phases) == {"job a", "job b"} and "compute" in phases["job a"]["phases"]
    table = runner.table()
    row = table.set_index("job").loc["job a"]
    assert row["start-up and rest"] == pytest.approx(row["wall s"] - row["compute"])
    assert 0 <= row["compute"] <= row["wall s"]
    path = runner.write_profile(total=timings["experiments"])
    assert "| experiments | job a |" in path.read_text()
    walls = json.loads((tmp_path / "paper" / "paper.profile.json").read_text())["walls"]
    assert set(walls) == {"job a", "job b"}
    assert runner._order() == walls  # the next run starts the longest job first


def test_threads_per_job_never_drops_below_one(monkeypatch):
    monkeypatch.setattr(jobs_mod.os, "cpu_count", lambda: 2)
    assert [threads_per_job(w) for w in (1, 2, 3, 8)] == [2, 1, 1, 1]


def test_stages_held_together_run_in_one_pool_and_then_follow_their_own_jobs(child, tmp_path, monkeypatch):
    """Two stages held by `together` run side by side (each job waits for the other's marker: run one stage after
    the other, neither finishes); the wall goes to `"a + b"`, the profile keeps each job's own stage, each stage's
    `then` runs after the pool and only if its own jobs succeeded; once closed, a stage starts nothing."""
    job, out = child
    timings: dict[str, float] = {}
    runner = _runner(tmp_path, monkeypatch, timings, stop=False)
    after = []
    with runner.together():
        assert not runner.stage("certify", [job("a", "b")], then=lambda: after.append("certify"))
        assert not runner.stage("experiments", [job("b", "a")], then=lambda: after.append("experiments"))
        assert after == [] and not (out / "order.txt").exists()  # held until the block ends
    assert after == ["certify", "experiments"] and set(timings) == {"certify + experiments"}
    assert {s: d.job.label for s, d in runner.done} == {"certify": "job a", "experiments": "job b"}
    with runner.together():
        runner.stage("bracket", [job("bad", rc=3)], then=lambda: after.append("bracket"))
        runner.stage("learned", [job("c")], then=lambda: after.append("learned"))
    assert after[2:] == ["learned"]  # the failed stage's `then` does not run
    runner.closed = True
    assert not runner.stage("again", [job("d")]) and not (out / "d.threads").exists()


def test_a_job_waits_for_the_job_of_its_pool_that_makes_a_folder_its_command_names(child, tmp_path, monkeypatch):
    """`make paper` holds every stage after the data in one pool: an error map waits for its map's training, an
    experiment for the maps and error maps it is pinned to (their folders named on its command line, `made_by`), and
    a job whose inputs are built already (or made by nobody in the pool) waits for nothing."""
    job, out = child
    runner = _runner(tmp_path, monkeypatch, {}, stop=True)
    runner.made_by.update({"mapx-0123456789": "job train", "mapx-9876543210": "job errormap"})

    def reader(me, *pins):
        return Job("fake", [str(out), me, "-", "0", *pins], f"job {me}", module="fake_stage")

    with runner.together():
        runner.stage("experiments", [reader("both", "maps.a=mapx-0123456789", "errormaps.a=mapx-9876543210"),
                                     reader("free", "maps.a=mapy-0123456789", "maps.b=mapx-0123456789_copy")])
        runner.stage("errormap", [reader("errormap", "maps=[mapx-0123456789]")])
        runner.stage("train", [job("train")])
    after = {d.job.label: d.job.after for _, d in runner.done}
    assert after == {"job both": ("job train", "job errormap"), "job free": (), "job errormap": ("job train",),
                     "job train": ()}
    order = (out / "order.txt").read_text().split()
    assert order.index("train") < order.index("errormap") < order.index("both")
