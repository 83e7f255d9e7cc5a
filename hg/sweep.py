"""Sweeps on Ray: each job is a command run in a child process by one Ray task, on a local Ray instance or on a
cluster (`address`, or the RAY_ADDRESS variable). The command writes its own result file, so a job is done when
that file exists, with or without Ray; a failing job fails alone. Ray is imported here only when a sweep runs."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

OBJECT_STORE_BYTES = 100 * 2**20  # the jobs pass no data through Ray: a small store starts fast beside a small /dev/shm


@dataclass(frozen=True)
class Job:
    """One command of a sweep, run in a child process; it writes `done` when it succeeds."""

    name: str
    command: tuple[str, ...]
    log: Path  # the child's stdout and stderr, appended
    done: Path  # the file the command writes when it succeeds
    env: Mapping[str, str] = field(default_factory=dict)  # set over the Ray worker's environment
    after: tuple[str, ...] = ()  # names of earlier jobs of the sweep that must end before this one starts


class Stopped(Exception):
    """A sweep stopped by a signal: its pending jobs were cancelled, its running children stopped by SIGTERM."""

    def __init__(self, signal_name: str, unfinished: int):
        super().__init__(f"stopped by {signal_name}; {unfinished} jobs unfinished")
        self.signal_name, self.unfinished = signal_name, unfinished


def run_child(name: str, command: Sequence[str], log: Path, done: Path, env: Mapping[str, str], cwd: Path,
              *after) -> tuple[int, bool, float]:
    """A Ray task: the job's command in a child process, its output appended to the log after a header naming the
    host and task. Cancelling the task (a KeyboardInterrupt here) sends the child SIGTERM and waits for it, so a
    Lightning fit ends at its next step and resumes next time. Returns the exit code, whether `done` was written and
    the seconds taken. `after`: the results of the jobs this one waits for (Ray resolves them first)."""
    import ray

    log.parent.mkdir(parents=True, exist_ok=True)
    start = time.time()
    # a cancel interrupts through Python's SIGINT handler, absent when the sweep was started with SIGINT ignored (a
    # shell's background job): the child would run on
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with open(log, "a") as stream:
            stream.write(f"== {name} on {socket.gethostname()} (Ray task {ray.get_runtime_context().get_task_id()}): "
                         f"{' '.join(command)}\n")
            stream.flush()
            child = subprocess.Popen(command, stdout=stream, stderr=subprocess.STDOUT, env={**os.environ, **env},
                                     cwd=cwd)
            try:
                while True:
                    try:
                        code = child.wait(timeout=1)  # a timeout, so that a cancel's interrupt is seen
                        break
                    except subprocess.TimeoutExpired:
                        pass
            except KeyboardInterrupt:
                child.send_signal(signal.SIGTERM)
                code = child.wait()
    finally:
        signal.signal(signal.SIGINT, previous)
    return code, done.is_file(), time.time() - start


def start_ray(address: str | None, cpus: int) -> str:
    """Join the cluster at `address` (or RAY_ADDRESS), or start a local instance with `cpus` CPUs. Says where."""
    import ray

    address = address or os.environ.get("RAY_ADDRESS")
    quiet = {"include_dashboard": False, "log_to_driver": False, "logging_level": "warning"}
    if address and address != "local":
        ray.init(address=address, **quiet)
        return f"the Ray cluster at {address}"
    # Ray raises its workers' niceness by 15 (19 under a sweep at nice 5), so any other work on the machine starved
    # the runs; a local instance's workers keep the sweep's own niceness instead (set it with `nice`), unless the
    # user set Ray's variable
    os.environ.setdefault("RAY_worker_niceness", "0")
    ray.init(address="local", num_cpus=cpus, object_store_memory=OBJECT_STORE_BYTES, **quiet)
    return f"a local Ray instance (num_cpus={cpus})"


def run_jobs(jobs: Sequence[Job], cpus_per_job: int, at_once: int, cwd: Path, address: str | None = None) -> int:
    """Run the jobs as Ray tasks of `cpus_per_job` CPUs each: on this machine at most `at_once` at a time, on a
    cluster as many as its CPUs hold. Prints a line per ended job (name, state, seconds, how many ended). SIGTERM or
    Ctrl-C cancels the pending jobs and stops the running children, then raises Stopped. Returns how many jobs did
    not write their `done` file or exited non-zero."""
    names = [job.name for job in jobs]
    for i, job in enumerate(jobs):
        if job.name in names[:i]:
            raise ValueError(f"job {job.name}: twice in the sweep")
        if missing := [a for a in job.after if a not in names[:i]]:
            raise ValueError(f"job {job.name}: waits for {missing}, not earlier jobs of the sweep")
    if not jobs:
        return 0
    import ray

    where = start_ray(address, cpus_per_job * at_once)
    stopping: list[str] = []

    def stop(signum: int, frame) -> None:
        stopping.append(signal.Signals(signum).name)

    previous = {s: signal.signal(s, stop) for s in (signal.SIGTERM, signal.SIGINT)}  # after ray.init: it sets its own
    try:
        largest = max((node["Resources"].get("CPU", 0) for node in ray.nodes() if node["Alive"]), default=0)
        if cpus_per_job > largest:
            raise ValueError(f"{cpus_per_job} CPUs per job: no node of {where} has that many (the largest {largest:g})")
        print(f"{len(jobs)} jobs on {where}, each a task of num_cpus={cpus_per_job}", flush=True)
        task = ray.remote(run_child).options(num_cpus=cpus_per_job, max_retries=0)
        refs: dict = {}
        for job in jobs:
            refs[job.name] = task.remote(job.name, job.command, job.log, job.done, dict(job.env), cwd,
                                         *(refs[a] for a in job.after))
        by_ref = {ref: job for job, ref in zip(jobs, refs.values())}
        pending, failed, cancelled = list(by_ref), 0, False
        while pending:
            if stopping and not cancelled:
                for ref in pending:
                    ray.cancel(ref)
                cancelled = True
            ready, pending = ray.wait(pending, timeout=1.0)
            for ref in ready:
                job = by_ref[ref]
                try:
                    code, written, seconds = ray.get(ref)
                except ray.exceptions.TaskCancelledError:
                    state, written, code = "not started (stopping)", False, None
                except ray.exceptions.RayError as exc:
                    state, written, code = f"FAILED ({type(exc).__name__}), see {job.log}", False, None
                else:  # a Lightning fit stopped by SIGTERM exits 0 without its file: not done
                    state = (("done" if written else f"stopped before writing {job.done.name}, see {job.log}")
                             if code == 0 else f"FAILED (exit {code}), see {job.log}") + f" in {seconds:.0f} s"
                failed += not (written and code == 0)
                print(f"{job.name}: {state} [{len(jobs) - len(pending)}/{len(jobs)} ended]", flush=True)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        ray.shutdown()
    if stopping:
        raise Stopped(stopping[0], failed)
    return failed
