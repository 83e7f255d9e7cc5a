"""Swap every serial arm that ships with pybullet_data, and the structures in tests/data/robots, and report each.

    .venv/bin/python scripts/robot_survey.py --write docs/robots.md

An arm in pybullet_data is any URDF there with at least `--min-joints` (5) movable joints on one path from the root
to a leaf (legged robots have 3 per leg). Each goes through `swap_robot` exactly as scripts/swap_urdf.py runs it
(no --tool-link, no --base: the tool link and base placement are the swap's own choices), into a temporary folder;
nothing is committed but the report. The report's table lands between the survey markers of the --write file. The
last line printed is JSON: one entry per arm with its reach fraction, or the one-line refusal.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
import time
from pathlib import Path

import pybullet_data

from hg.atomic import write_atomic
from hg.sim.urdf_tools import leaf_links, load_urdf, movable_joints, swap_robot

ROOT = Path(__file__).resolve().parents[1]
WRITTEN = ROOT / "tests" / "data" / "robots"
DATA = Path(pybullet_data.getDataPath())
BEGIN, END = "<!-- robot survey: begin (scripts/robot_survey.py writes this part) -->", "<!-- robot survey: end -->"


def longest_chain(path: Path) -> int:
    """Movable joints on the longest root-to-leaf path; 0 for files that are not a robot we can read."""
    try:
        robot = load_urdf(path).robot
    except (ValueError, FileNotFoundError):
        return 0
    return max((movable_joints(robot, leaf) for leaf in leaf_links(robot)), default=0)


def bundled_arms(min_joints: int) -> list[Path]:
    return [p for p in sorted(DATA.rglob("*.urdf")) if longest_chain(p) >= min_joints]


def written_arms() -> list[Path]:
    return sorted(p for p in WRITTEN.rglob("*") if p.suffix in (".urdf", ".xacro"))


def survey(path: Path, n_verify: int, seed: int) -> dict:
    name = str(path.relative_to(DATA)) if DATA in path.parents else str(path.relative_to(ROOT))
    entry = {"arm": name, "source": "pybullet_data" if DATA in path.parents else "written"}
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="hg-survey-") as tmp:
        try:
            result = swap_robot(path, Path(tmp) / "arm_probe.urdf", visuals="collision", n_verify=n_verify,
                                seed=seed, generator="scripts/robot_survey.py")
        except (ValueError, FileNotFoundError) as exc:
            message = re.sub(r"robot URDF \S+: ", "", str(exc)).replace(str(DATA), "pybullet_data")
            entry["refused"] = message.replace(str(ROOT) + "/", "")
        else:
            summary = result.summary()
            entry.update(joints=summary["joints"], tool_link=summary["tool_link"],
                         reach_fraction=summary["reach_fraction"],
                         n_requests=summary["n_requests"], base_position=summary["base_position"],
                         base_rpy_deg=summary["base_rpy_deg"], base=str(result.base),
                         misses=result.report.split("where it fails", 1)[-1].strip() if result.reach.fraction < 1
                         else "")
    entry["seconds"] = round(time.perf_counter() - start, 1)
    return entry


def table(entries: list[dict], command: str) -> str:
    lines = [BEGIN, "", f"Written by `{command}`; each arm swapped with no `--tool-link` and no `--base`, reach "
             f"counted within 5 mm and 3 degrees on random requests.", "",
             "| arm | source | joints on the chain | tool link found | base placement | reach |",
             "|---|---|---|---|---|---|"]
    for e in entries:
        if "refused" in e:
            lines.append(f"| `{e['arm']}` | {e['source']} | | | refused: {e['refused']} | |")
        else:
            lines.append(f"| `{e['arm']}` | {e['source']} | {e['joints']} | `{e['tool_link']}` | {e['base']} | "
                         f"{e['reach_fraction']:.4f} of {e['n_requests']} |")
    return "\n".join(lines + ["", END])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n-verify", type=int, default=2000, help="random requests for each arm's reach fraction")
    parser.add_argument("--min-joints", type=int, default=5, help="what counts as an arm in pybullet_data")
    parser.add_argument("--only", nargs="*", help="survey only arms whose path contains one of these strings")
    parser.add_argument("--write", type=Path, help="markdown file whose survey section is replaced")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.write is not None and not (args.write.is_file() and BEGIN in args.write.read_text()
                                       and END in args.write.read_text()):
        print(f"robot_survey.py: error: --write {args.write}: no file with the survey markers {BEGIN!r} ... {END!r}",
              file=sys.stderr)
        return 2
    arms = [p for p in bundled_arms(args.min_joints) + written_arms()
            if not args.only or any(s in str(p) for s in args.only)]
    entries = []
    for path in arms:
        entries.append(survey(path, args.n_verify, args.seed))
        print(json.dumps(entries[-1]), flush=True)
    if args.write is not None:
        text = args.write.read_text()
        command = "scripts/robot_survey.py " + " ".join(argv if argv is not None else sys.argv[1:])
        section = table(entries, command.strip())
        write_atomic(args.write, text[:text.index(BEGIN)] + section + text[text.index(END) + len(END):])
    print(json.dumps({"arms": entries}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
