"""Golden numbers of the pre-refactor HapticGlance (commit 743bddf): a tiny ideal-mode rollout and its loss terms at
a fixed seed for four configs, with the tiny model's weights, so that tests/test_golden.py checks the composed
model of the refactor gives the same numbers from the same weights. It reads the old flags, so it runs only on
the old code, where it was run once (commit 3541413, whose code is 743bddf's):
    git checkout 3541413 && WANDB_MODE=disabled .venv/bin/python tests/golden/record.py
"""
import json
from pathlib import Path

import torch

from hg.lightning.cli import cli
from hg.lightning.data import episode_batch

HERE = Path(__file__).parent
CONFIGS = {
    "paper": "configs/pcrn_fc.yaml",
    "fixed_scan": "configs/side_scan_touchset_wide_final_mirror_long_lr_decay.yaml",
    "gaussian_on_scan": "configs/pcrn_fc_side_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_final_mirror.yaml",
    "planner_copy": "configs/pcrn_fc_candidates_readings_only_imitate_planner65k_final_mirror_library_namer.yaml",
}
TINY = ["--data.mode", "ideal", "--data.n_probes", "4", "--data.batch_size", "8", "--data.eval_batch_size", "8",
        "--model.width", "16", "--model.representation", "32", "--model.hidden", "32", "--trainer.logger", "false",
        "--seed_everything", "0"]
SEED = 1234


def rounded(t: torch.Tensor) -> list:
    return t.detach().double().cpu().numpy().round(6).tolist()


def main() -> None:
    golden = {}
    for name, config in CONFIGS.items():
        torch.manual_seed(0)
        extra = ["--model.library_namer_episodes", "64"] if "library_namer" in config else []
        run = cli(["--config", config, *TINY, *extra], run=False)
        model, data = run.model, run.datamodule
        model.sim = data.make_simulator()
        if model.hparams.library_namer:
            model.library_namer = model.build_library_namer(model.hparams.library_namer, data)
        torch.save(model.state_dict(), HERE / f"{name}.pt")
        batch = episode_batch(data.regions, "train", 8, data.n_classes, [0, 0, 0, 0])
        labels, poses = batch["labels"], batch["poses"]
        record = {"labels": labels.tolist()}
        model.train()
        rollout = model.rollout(labels, poses, SEED)
        terms, logits = model.evaluate(rollout, labels)
        record["train"] = {"requests": rounded(rollout.requests), "points": rounded(rollout.points),
                           "logits": rounded(logits), "terms": {k: float(v) for k, v in terms.items()}}
        if model.hparams.prior != "none":  # the warm-up: the fixed scan the policy starts on
            scan = model.rollout(labels, poses, SEED, follow_scan=True)
            terms, _ = model.evaluate(scan, labels, learn_policy=False)
            record["scan"] = {"requests": rounded(scan.requests), "points": rounded(scan.points),
                              "terms": {k: float(v) for k, v in terms.items()}}
        if model.hparams.imitate:  # copying the rollout's own requests as if a teacher had chosen them
            terms, _ = model.evaluate(rollout, labels, learn_policy="imitate")
            record["imitate"] = {"terms": {k: float(v) for k, v in terms.items()}}
        model.eval()
        with torch.no_grad():
            deterministic = model.hparams.policy == "learned"
            rollout = model.rollout(labels, poses, SEED, deterministic=deterministic)
            _, logits = model.evaluate(rollout, labels)
            if model.library_namer is not None:
                named = model.library_log_posterior(rollout)
                record["eval_named"] = rounded(named)
                logits = logits + named
        record["eval"] = {"requests": rounded(rollout.requests), "points": rounded(rollout.points),
                          "logits": rounded(logits)}
        model.sim.close()
        golden[name] = record
    (HERE / "golden.json").write_text(json.dumps(golden, indent=1) + "\n")


if __name__ == "__main__":
    main()
