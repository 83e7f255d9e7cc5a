"""hg.sweep on a local Ray instance: a job waits for the jobs it names, a failing or silent job fails alone, each log
names the Ray task that ran it, and a job runs at the sweep's niceness; a job waiting for a later one, or named twice,
is refused before Ray starts."""
import os
import sys

import pytest

from hg.sweep import Job, run_jobs


def python(code: str) -> tuple[str, ...]:
    return (sys.executable, "-c", f"import os, pathlib, sys, time; {code}")


def test_jobs_run_as_ray_tasks_in_order_and_fail_alone(tmp_path, capsys):
    done = {name: tmp_path / f"{name}.done" for name in ("first", "second", "broken", "silent")}
    jobs = [Job("first", python(f"time.sleep(1); pathlib.Path({str(done['first'])!r}).write_text('1')"),
                tmp_path / "logs" / "first.txt", done["first"]),
            Job("broken", python("sys.exit(3)"), tmp_path / "logs" / "broken.txt", done["broken"]),
            Job("second", python(f"assert pathlib.Path({str(done['first'])!r}).is_file(); "
                                 f"pathlib.Path({str(done['second'])!r}).write_text(os.environ['ASKED'] + "
                                 "str(os.nice(0)))"),
                tmp_path / "logs" / "second.txt", done["second"], {"ASKED": "yes"}, after=("first",)),
            Job("silent", python("pass"), tmp_path / "logs" / "silent.txt", done["silent"])]
    assert run_jobs(jobs, cpus_per_job=1, at_once=2, cwd=tmp_path) == 2  # broken and silent
    # it ran after first, with its environment, at the sweep's niceness (not Ray's +15 for its workers)
    assert done["second"].read_text() == f"yes{os.nice(0)}"
    out = capsys.readouterr().out
    assert "4 jobs on a local Ray instance (num_cpus=2), each a task of num_cpus=1" in out
    assert "broken: FAILED (exit 3), see " in out and "silent: stopped before writing silent.done, see " in out
    assert "first: done in" in out and "[4/4 ended]" in out
    assert (tmp_path / "logs" / "second.txt").read_text().startswith("== second on ")
    assert "(Ray task " in (tmp_path / "logs" / "broken.txt").read_text()


def test_a_job_waiting_for_a_later_job_or_named_twice_is_refused(tmp_path):
    jobs = [Job("a", python("pass"), tmp_path / "a.txt", tmp_path / "a", after=("b",)),
            Job("b", python("pass"), tmp_path / "b.txt", tmp_path / "b")]
    with pytest.raises(ValueError, match=r"job a: waits for \['b'\], not earlier jobs of the sweep"):
        run_jobs(jobs, cpus_per_job=1, at_once=1, cwd=tmp_path)
    with pytest.raises(ValueError, match="job b: twice in the sweep"):
        run_jobs([jobs[1], jobs[1]], cpus_per_job=1, at_once=1, cwd=tmp_path)
