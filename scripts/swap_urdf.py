"""Swap in another robot: attach our probe to a URDF arm, place its base beside the probe line, report reach.

    python scripts/swap_urdf.py kuka_iiwa/model.urdf --tool-link lbr_iiwa_link_7 --visuals collision
        --out urdf/kuka_iiwa_probe.urdf

ROBOT.urdf is a path, or a path inside the installed pybullet_data. The last line printed is JSON with
reach_fraction, base_position, base_rpy_deg and out. Errors print one line and exit with status 2.
"""
from __future__ import annotations

import argparse
import json
import sys

from hg.sim.urdf_tools import VISUALS, BasePlacement, SwapResult, swap_robot


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("robot", help="robot URDF: a path, or a path inside pybullet_data (kuka_iiwa/model.urdf)")
    parser.add_argument("--out", required=True, help="URDF to write; meshes go to meshes/<out stem>/ beside it")
    parser.add_argument("--tool-link", help="link that carries the probe (default: the tree's only leaf)")
    parser.add_argument("--base", nargs=3, type=float, metavar=("X", "Y", "Z"),
                        help="place the base here instead of searching")
    parser.add_argument("--tilt", type=float, default=0.0, help="with --base: tilt (deg) towards the probe line")
    parser.add_argument("--yaw", type=float, default=0.0, help="with --base: yaw (deg) about the base's z axis")
    parser.add_argument("--mount-offset", type=float,
                        help="rod start along the tool link's +z in m (default: the far face of its geometry)")
    parser.add_argument("--visuals", choices=VISUALS, default="copy",
                        help="'collision' draws links with their collision meshes: a smaller commit")
    parser.add_argument("--n-verify", type=int, default=2000, help="random requests for the reach fraction")
    parser.add_argument("--n-check", type=int, default=500, help="random requests per base candidate verified")
    parser.add_argument("--min-reach", type=float, default=0.5, help="fail below this reach fraction")
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args(argv)


def run(args: argparse.Namespace) -> SwapResult:
    base = BasePlacement(*args.base, tilt_deg=args.tilt, yaw_deg=args.yaw) if args.base else None
    return swap_robot(args.robot, args.out, tool_link=args.tool_link, base=base, visuals=args.visuals,
                      mount=args.mount_offset, n_verify=args.n_verify, n_check=args.n_check,
                      min_reach=args.min_reach, seed=args.seed, generator="scripts/swap_urdf.py",
                      log=lambda line: print(line, flush=True))


def main(argv: list[str] | None = None) -> int:
    try:
        result = run(parse_args(argv))
    except (ValueError, FileNotFoundError) as exc:
        print(f"swap_urdf.py: error: {exc}", file=sys.stderr)
        return 2
    print(result.report)
    print(json.dumps(result.summary()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
