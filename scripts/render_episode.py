"""See what the robot does: one held-out episode per class played by a checkpoint, rendered.

Writes into --out, per class: a PNG per probe (the arm at that probe's pose, rays and touches so far), a GIF of
them, and the touched points over the object mesh; with --maps also where the policy probes over the whole split
and the confusion matrices. The model is the checkpoint's composition (its encoder, policy and heads, rebuilt from
its hyperparameters); the predictions shown are its learned heads' (`model.predict`, no library classifier). The
world comes from the checkpoint's datamodule settings through the `hg` CLI, with --config files (in order) and
--mode applied on top. The last line printed is JSON listing the files.

    python scripts/render_episode.py --ckpt runs/haptic-glance/<id>/checkpoints/last.ckpt --out docs/img
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


from hg.lightning.cli import datamodule_from_checkpoint
from hg.lightning.module import HapticGlance
from hg.lightning.viz import (Rollouts, arm_simulator, one_per_class, render_episodes, roll_out, rollout_kind,
                              write_test_maps)
from hg.sim.render import Camera


def main(argv: list[str]) -> list[Path]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ckpt", required=True, type=Path, help="checkpoint written by `hg fit`")
    parser.add_argument("--out", required=True, type=Path, help="folder for the pictures")
    parser.add_argument("--config", action="append", default=[],
                        help="config applied over the checkpoint's data settings (repeatable)")
    parser.add_argument("--split", choices=("val", "test"), default="val",
                        help="the episodes to draw (default val: a diagnostic never reads the test split unasked)")
    parser.add_argument("--mode", choices=("arm", "ideal"),
                        help="probing mode of the rollouts (default: the checkpoint's); frames always show the arm")
    parser.add_argument("--mean-action", action="store_true", help="the mean-action policy instead of a sampled one")
    parser.add_argument("--maps", action="store_true",
                        help="also the probe heat maps and confusion matrices over the whole split")
    parser.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"), help="frame size")
    args = parser.parse_args(argv)
    if not args.ckpt.is_file():
        raise FileNotFoundError(f"--ckpt {args.ckpt}: file not found")

    datamodule = datamodule_from_checkpoint(args.ckpt, args.config, ["--data.mode", args.mode] if args.mode else [])
    model = HapticGlance.load_from_checkpoint(args.ckpt, map_location="cpu").eval()
    if model.hparams.n_classes != datamodule.n_classes:
        raise ValueError(f"{args.ckpt}: the model knows {model.hparams.n_classes} classes, the data "
                         f"{datamodule.n_classes} ({', '.join(datamodule.class_names)}); check --config")
    loader = datamodule.test_dataloader() if args.split == "test" else datamodule.val_dataloader()
    model.attach(datamodule.make_simulator())  # the touch sets' mirror line is the simulator's probe line
    try:
        parts = []
        for batch in loader:  # whole batches, so each episode's rollout is the one the evaluation scored
            parts.append(roll_out(model, batch, deterministic=args.mean_action))
            found = one_per_class(Rollouts.concat(parts), datamodule.n_classes)
            if not args.maps and len(found) == datamodule.n_classes:
                break
        rollouts = Rollouts.concat(parts)
        picked = one_per_class(rollouts, datamodule.n_classes)
        own = model.sim.arm is None or not model.sim.visuals  # frames need the arm and the looks
        sim = arm_simulator(datamodule) if own else model.sim
        try:
            written = render_episodes(rollouts, picked, sim, datamodule.class_names, args.out, Camera(*args.size))
        finally:
            if own:
                sim.close()
    finally:
        model.sim.close()
    if args.maps:
        written += write_test_maps(rollouts, datamodule.class_names, datamodule.scene, args.out)
    names = datamodule.class_names
    episodes = [{"index": i, "class": names[int(rollouts.labels[i])],
                 "predictions": [names[int(p)] for p in rollouts.predictions[i]],
                 "touches": int(rollouts.points[i, :, 3].sum())} for i in picked]
    for episode in episodes:
        print(f"{args.split} episode {episode['index']} ({episode['class']}): predictions after each probe "
              f"{' '.join(episode['predictions'])}; {episode['touches']} touches")
    print(f"{len(written)} files in {args.out} ({rollout_kind(args.mean_action)}, {datamodule.hparams.mode} mode)")
    print(json.dumps({"out": str(args.out), "rollout": rollout_kind(args.mean_action), "mode": datamodule.hparams.mode,
                      "split": args.split, "episodes": episodes, "files": [str(p) for p in written]}))
    return written


if __name__ == "__main__":
    try:
        main(sys.argv[1:])
    except (ValueError, FileNotFoundError) as exc:  # one line naming the file or field, as `hg` does
        print(f"render_episode: error: {exc}", file=sys.stderr)
        sys.exit(2)
