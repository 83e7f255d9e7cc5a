"""Where a figure came from: the commit of the code that produced it and the machine it ran on."""
from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# the files that decide a training or evaluation result: the code, the configs, the robots, the teacher files a policy
# copies, and the scripts (a planner row's numbers are scripts/plan.py's, a row's composition is in reproduce_table1.py)
RESULT_PATHS = ("hg", "configs", "urdf", "data", "scripts")


def commit(paths: tuple[str, ...] = RESULT_PATHS) -> str:
    """HEAD's short hash, with '+dirty' when tracked files under `paths` differ from it (edits elsewhere, say
    to docs while a long run is going, do not change a result)."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()

    head = git("rev-parse", "--short", "HEAD") or "unknown"
    return head + ("+dirty" if git("status", "--porcelain", "--untracked-files=no", "--", *paths) else "")


def hardware() -> str:
    """CPU model, core count, Python and torch versions."""
    import torch

    cpuinfo = Path("/proc/cpuinfo")
    models = [line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines()
              if line.startswith("model name")] if cpuinfo.exists() else []
    cpu = models[0] if models else platform.processor() or platform.machine()
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, torch {torch.__version__}"


def repo_path(path: str | Path) -> str:
    """A path as results record it: relative to the repository when inside it (portable), else absolute."""
    path = Path(path).resolve()
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)
