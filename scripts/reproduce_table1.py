"""Reproduce the paper's Table 1 side by side: every row trained with the paper protocol, several seeds, all
scored on the same held-out test episodes, merged into docs/results/table1.{md,json,png}.

Each (row, seed) is one training run in a child process. A finished run leaves a small JSON in
`<out>/runs/`; it is never recomputed, so rows can be run separately (even on other machines) and merged, and
an interrupted run resumes from its last checkpoint in `<runs-dir>`. The merge reads every run JSON present.

    .venv/bin/python scripts/reproduce_table1.py                           # every row, seeds 0 1 2, then merge
    .venv/bin/python scripts/reproduce_table1.py --rows lstm --seeds 0     # one run, then merge what exists
    .venv/bin/python scripts/reproduce_table1.py --merge-only

The last line printed is JSON: for each row its mean accuracy after each probe, and the commit.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hg.atomic import write_atomic  # noqa: E402
from hg.provenance import commit, hardware, repo_path  # noqa: E402

TEST_EPISODES = 2048  # the fixed held-out test set every row is scored on (data.eval_seed 0)
EVAL_SEED = 0
SEEDS = (0, 1, 2)  # training seeds of every row (the protocol)


@dataclass(frozen=True)
class Row:
    """A row of the table; its config is configs/<row name>.yaml (config_of)."""
    label: str
    paper: str | None = None  # the paper's column this row reproduces
    learned: bool = True
    encoder: str = "pcrn"
    planner: tuple[str, ...] = ()  # a row that plans instead of learning: scripts/plan.py's library arguments
    planned: str = "planner"  # which of plan.py's results a planner row reports: its "planner", or probes
    # placed by no one ("fixed": the straight scan, "random") named by the same weighing of its library
    namer_of: str | None = None  # the row whose library namer names this row's probes: the policy's margin over
    # them is read with that row's namer alone on both sides (the same classifier)
    scores: str | None = None  # a row that trains nothing: it scores that row's best checkpoints (same seed) as its
    # config reads them (e.g. with model.library_namer), so it runs after that row


SIDE_SCAN = "side-picking scan (steep first pair) + PCRN-FC + wide touch set"
FINAL_TOUCH_SET = "a touch set of its own after the 10th probe"
LONG_DECAY = "16000 steps, learning rate falling to 5%"
SIDE_LEARNED = ("PCRN-FC+ from the side-picking scan (steep first pair) + wide touch set, std shrinking to a tenth, 16000 "
                "steps with the policy from step 8000, policy starting exactly on the scan and held near it, learning "
                f"rate falling to 5%, {FINAL_TOUCH_SET}")
# the planner's library: training episodes with their moves along the line and mirror images (docs/training.md)
PLANNER_LIBRARY = ("--library-split", "train", "--library", "32768", "--shifts", "5", "--mirror")
PLANNER_LIBRARY_65K = tuple("65536" if arg == "32768" else arg for arg in PLANNER_LIBRARY)  # twice the poses
# the library of the namer of the copy of the 65536-pose teachers (model.library_namer data/planner/train65k_s10.npz)
NAMER_65K = "pcrn_fc_candidates_readings_only_imitate_planner65k_final_mirror_library_namer"
NAMER_65K_LIBRARY = (*PLANNER_LIBRARY_65K, "--library-seed", "10", "--no-planner")
ROWS = {
    "pcrn_fc": Row("PCRN-FC", paper="PCRN-FC"),
    "pcrn_nclass": Row("PCRN-N-class", paper="PCRN-N-class"),
    "lstm": Row("LSTM", paper="LSTM", encoder="lstm"),
    "random": Row("random probes + PCRN-FC", learned=False),
    "line_scan": Row("line scan + PCRN-FC", learned=False),
    "pcrn_fc_plus": Row("PCRN-FC+ (beyond the paper)"),
    "centre_scan": Row("centre-out scan + PCRN-FC (beyond the paper)", learned=False),
    "pcrn_fc_centre": Row("PCRN-FC+ from the centre-out scan (beyond the paper)"),
    "centre_scan_touchset": Row("centre-out scan + PCRN-FC + touch set (beyond the paper)", learned=False),
    "pcrn_fc_centre_touchset": Row("PCRN-FC+ from the centre-out scan + touch set (beyond the paper)"),
    "pcrn_fc_centre_touchset_warmup": Row("PCRN-FC+ from the centre-out scan + touch set, policy from step 4000 "
                                          "(beyond the paper)"),
    "fan_scan_touchset": Row("fanned scan + PCRN-FC + touch set (beyond the paper)",
                             learned=False),
    "follow_scan_touchset": Row("centre-out scan following the touches + PCRN-FC + touch set (beyond the paper)",
                                learned=False),
    "fan_follow_scan_touchset": Row("fanned scan following the touches + PCRN-FC + touch set (beyond the paper)",
                                    learned=False),
    "centre_scan_touchset_wide": Row("centre-out scan + PCRN-FC + wide touch set (beyond the paper)", learned=False),
    "side_scan_touchset_wide": Row(f"{SIDE_SCAN} (beyond the paper)", learned=False),
    "side_scan_touchset_wide_long_lr_decay": Row(f"{SIDE_SCAN}, {LONG_DECAY} (beyond the paper)", learned=False),
    "side_scan_touchset_wide_final_long_lr_decay": Row(f"{SIDE_SCAN}, {FINAL_TOUCH_SET}, {LONG_DECAY} (beyond the "
                                                       "paper)", learned=False),
    "side_scan_touchset_wide_final_mirror_long_lr_decay": Row(
        f"{SIDE_SCAN}, {FINAL_TOUCH_SET}, both reading an episode and its mirror image across the line alike, "
        f"{LONG_DECAY} (beyond the paper)", learned=False),
    "centre_scan_touchset_wide_long": Row("centre-out scan + PCRN-FC + wide touch set, 16000 steps (beyond the "
                                          "paper)", learned=False),
    "centre_scan_touchset_wide_lr_decay": Row("centre-out scan + PCRN-FC + wide touch set, learning rate falling to "
                                              "5% (beyond the paper)", learned=False),
    "centre_scan_touchset_wide_long_lr_decay": Row("centre-out scan + PCRN-FC + wide touch set, 16000 steps, learning "
                                                   "rate falling to 5% (beyond the paper)", learned=False),
    "centre_scan_touchset_wide_32k_lr_decay": Row("centre-out scan + PCRN-FC + wide touch set, 32000 steps, learning "
                                                  "rate falling to 5% (beyond the paper)", learned=False),
    "coarse_scan_touchset_wide_lr_decay": Row("coarse-first scan + PCRN-FC + wide touch set, learning rate falling "
                                              "to 5% (beyond the paper)", learned=False),
    "coarse_scan_touchset_wide_prefix_lr_decay": Row("coarse-first scan + PCRN-FC + wide touch set told the prefix, "
                                                     "learning rate falling to 5% (beyond the paper)", learned=False),
    "centre_scan_touchset_wide_prefix_lr_decay": Row("centre-out scan + PCRN-FC + wide touch set told the prefix, "
                                                     "learning rate falling to 5% (beyond the paper)", learned=False),
    "follow2_scan_touchset_wide_lr_decay": Row("centre-out scan following its first touch for 2 probes + PCRN-FC + "
                                               "wide touch set, learning rate falling to 5% (beyond the paper)",
                                               learned=False),
    "centre_scan_touchset_alone_lr_decay": Row("centre-out scan + wide touch set alone, no PCRN, learning rate "
                                               "falling to 5% (beyond the paper)", learned=False),
    "follow2_scan_touchset_alone_lr_decay": Row("centre-out scan following its first touch for 2 probes + wide touch "
                                                "set alone, no PCRN, learning rate falling to 5% (beyond the paper)",
                                                learned=False),
    "centre_scan_touchset_wide_last_lr_decay": Row("centre-out scan + PCRN-FC + wide touch set scored after the 10th "
                                                   "probe only, learning rate falling to 5% (beyond the paper)",
                                                   learned=False),
    "follow2_scan_touchset_wide_last_lr_decay": Row("centre-out scan following its first touch for 2 probes + "
                                                    "PCRN-FC + wide touch set scored after the 10th probe only, "
                                                    "learning rate falling to 5% (beyond the paper)", learned=False),
    "follow2_scan_touchset_wide_final_lr_decay": Row("centre-out scan following its first touch for 2 probes + PCRN-FC "
                                                     "+ wide touch set, a touch set of its own after the 10th probe, "
                                                     "learning rate falling to 5% (beyond the paper)", learned=False),
    "coarse_scan_touchset_wide_final_lr_decay": Row("coarse-first scan + PCRN-FC + wide touch set, a touch set of its own after the "
                                                    "10th probe, learning rate falling to 5% (beyond the paper)",
                                                    learned=False),
    "coarse_follow2_scan_touchset_wide_final_lr_decay": Row(
        "coarse-first scan following its first touch for 2 probes + PCRN-FC + wide touch set, a touch set of its own "
        "after the 10th probe, learning rate falling to 5% (beyond the paper)", learned=False),
    "centre_scan_touchset_wide_ema": Row("centre-out scan + PCRN-FC + wide touch set, moving average of the weights "
                                         "(beyond the paper)", learned=False),
    "pcrn_fc_centre_touchset_warmup_wide": Row("PCRN-FC+ from the centre-out scan + wide touch set, policy from step "
                                               "4000 (beyond the paper)"),
    "pcrn_fc_centre_touchset_warmup_wide_std_decay": Row(
        "PCRN-FC+ from the centre-out scan + wide touch set, policy from step 4000, std shrinking to a tenth "
        "(beyond the paper)"),
    "pcrn_fc_centre_touchset_warmup_wide_std_decay_lean": Row(
        "PCRN-FC+ from the centre-out scan + wide touch set, policy from step 4000, std shrinking to a tenth, room "
        "to lean in the prior (beyond the paper)"),
    "pcrn_fc_centre_touchset_warmup_wide_std_decay_long": Row(
        "PCRN-FC+ from the centre-out scan + wide touch set, std shrinking to a tenth, 16000 steps with the policy "
        "from step 8000 (beyond the paper)"),
    "pcrn_fc_centre_touchset_warmup_wide_std_decay_exact": Row(
        "PCRN-FC+ from the centre-out scan + wide touch set, policy from step 4000, std shrinking to a tenth, "
        "policy starting exactly on the scan (beyond the paper)"),
    "pcrn_fc_centre_touchset_warmup_wide_std_decay_long_exact": Row(
        "PCRN-FC+ from the centre-out scan + wide touch set, std shrinking to a tenth, 16000 steps with the policy "
        "from step 8000, policy starting exactly on the scan (beyond the paper)"),
    "pcrn_fc_centre_touchset_warmup_wide_std_decay_exact_anchor": Row(
        "PCRN-FC+ from the centre-out scan + wide touch set, policy from step 4000, std shrinking to a tenth, "
        "policy starting exactly on the scan and held near it (beyond the paper)"),
    "pcrn_fc_centre_touchset_warmup_wide_std_decay_exact_mean_share": Row(
        "PCRN-FC+ from the centre-out scan + wide touch set, policy from step 4000, std shrinking to a tenth, "
        "policy starting exactly on the scan, half of each batch probed with its mean action (beyond the paper)"),
    "pcrn_fc_centre_touchset_warmup_wide_std_decay_exact_anchor_mean_share": Row(
        "PCRN-FC+ from the centre-out scan + wide touch set, policy from step 4000, std shrinking to a tenth, "
        "policy starting exactly on the scan and held near it, half of each batch probed with its mean action "
        "(beyond the paper)"),
    "pcrn_fc_centre_touchset_warmup_wide_std_decay_exact_anchor_lr_decay": Row(
        "PCRN-FC+ from the centre-out scan + wide touch set, policy from step 4000, std shrinking to a tenth, "
        "policy starting exactly on the scan and held near it, learning rate falling to 5% (beyond the paper)"),
    "pcrn_fc_centre_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay": Row(
        "PCRN-FC+ from the centre-out scan + wide touch set, std shrinking to a tenth, 16000 steps with the policy "
        "from step 8000, policy starting exactly on the scan and held near it, learning rate falling to 5% (beyond "
        "the paper)"),
    "pcrn_fc_centre_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_reads_touchset": Row(
        "PCRN-FC+ from the centre-out scan + wide touch set, std shrinking to a tenth, 16000 steps with the policy "
        "from step 8000, policy starting exactly on the scan and held near it, learning rate falling to 5%, the policy "
        "reading the touch set's pooled features (beyond the paper)"),
    "pcrn_fc_follow2_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay": Row(
        "PCRN-FC+ from the centre-out scan following its first touch for 2 probes + wide touch set, std shrinking to "
        "a tenth, 16000 steps with the policy from step 8000, policy starting exactly on the scan and held near it, "
        "learning rate falling to 5% (beyond the paper)"),
    "pcrn_fc_follow2_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_final": Row(
        "PCRN-FC+ from the centre-out scan following its first touch for 2 probes + wide touch set, std shrinking to "
        "a tenth, 16000 steps with the policy from step 8000, policy starting exactly on the scan and held near it, "
        "learning rate falling to 5%, a touch set of its own after the 10th probe (beyond the paper)"),
    "pcrn_fc_follow2_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_final_ema": Row(
        "PCRN-FC+ from the centre-out scan following its first touch for 2 probes + wide touch set, std shrinking to "
        "a tenth, 16000 steps with the policy from step 8000, policy starting exactly on the scan and held near it, "
        "learning rate falling to 5%, a touch set of its own after the 10th probe, moving average of the weights "
        "(beyond the paper)"),
    "pcrn_fc_coarse_follow2_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_final": Row(
        "PCRN-FC+ from the coarse-first scan following its first touch for 2 probes + wide touch set, std shrinking "
        "to a tenth, 16000 steps with the policy from step 8000, policy starting exactly on the scan and held near "
        "it, learning rate falling to 5%, a touch set of its own after the 10th probe (beyond the paper)"),
    "pcrn_fc_side_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_final": Row(
        f"{SIDE_LEARNED} (beyond the paper)"),
    "pcrn_fc_side_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_final_mirror": Row(
        f"{SIDE_LEARNED}, both touch sets reading an episode and its mirror image across the line alike (beyond the "
        "paper)"),
    "pcrn_fc_side_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_final_mirror_std05": Row(
        f"{SIDE_LEARNED}, both touch sets reading an episode and its mirror image across the line alike, the std "
        "shrinking to a twentieth instead (beyond the paper)"),
    "pcrn_fc_side_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_final_mirror_free_lean": Row(
        f"{SIDE_LEARNED}, both touch sets reading an episode and its mirror image across the line alike, the lean "
        "across the line left to the policy (beyond the paper)"),
    "pcrn_fc_side_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_final_mirror_free_py": Row(
        f"{SIDE_LEARNED}, both touch sets reading an episode and its mirror image across the line alike, where the "
        "probes enter the line left to the policy (beyond the paper)"),
    "pcrn_fc_side_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_final_mirror_anchor01": Row(
        f"{SIDE_LEARNED}, both touch sets reading an episode and its mirror image across the line alike, the anchor "
        "to the scan at a tenth of its weight (beyond the paper)"),
    "pcrn_fc_side_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_final_mirror_encoder": Row(
        f"{SIDE_LEARNED}, the whole model (encoder, classifiers, policy) reading an episode and its mirror image "
        "across the line alike (beyond the paper)"),
    "planner": Row("greedy information-gain planner over training episodes (moved along the line and mirrored), "
                   "Bayes classifier, no learning (beyond the paper)", learned=False, planner=PLANNER_LIBRARY),
    "planner65k": Row("greedy information-gain planner over twice as many training episodes (65536, moved along the "
                      "line and mirrored), Bayes classifier, no learning (beyond the paper)", learned=False,
                      planner=PLANNER_LIBRARY_65K),
    "candidate_scan_namer65k": Row("straight centre-out scan of the greedy planner's candidate places, named by the "
                                   "namer of the copy of the 65536-pose teachers alone, no learning (beyond the paper)",
                                   learned=False, planner=(*NAMER_65K_LIBRARY, "--fixed"), planned="fixed",
                                   namer_of=NAMER_65K),
    "random_candidates_namer65k": Row("random candidates of the greedy planner, named by the namer of the copy of the "
                                      "65536-pose teachers alone, no learning (beyond the paper)", learned=False,
                                      planner=(*NAMER_65K_LIBRARY, "--random"), planned="random", namer_of=NAMER_65K),
    "pcrn_fc_imitate_planner_final_mirror": Row(
        "PCRN-FC+ copying the greedy planner for 8000 steps, then the hybrid rule + wide touch set, std shrinking to a "
        f"tenth, 16000 steps, learning rate falling to 5%, {FINAL_TOUCH_SET}, both touch sets reading an episode and "
        "its mirror image across the line alike (beyond the paper)"),
    "pcrn_fc_candidates_imitate_planner_final_mirror": Row(
        "PCRN-FC+ choosing among the greedy planner's candidate probes, copying the planner for 8000 steps, then the "
        f"hybrid rule + wide touch set, temperature falling to a tenth, 16000 steps, learning rate falling to 5%, "
        f"{FINAL_TOUCH_SET}, both touch sets reading an episode and its mirror image across the line alike (beyond "
        "the paper)"),
    "pcrn_fc_candidates_reads_probes_imitate_planner_final_mirror": Row(
        "PCRN-FC+ choosing among the greedy planner's candidate probes from PCRN's state and what each candidate read "
        "so far, never one twice, copying the planner for 8000 steps, then the hybrid rule + wide touch set, "
        f"temperature falling to a tenth, 16000 steps, learning rate falling to 5%, {FINAL_TOUCH_SET}, both touch "
        "sets reading an episode and its mirror image across the line alike (beyond the paper)"),
    "pcrn_fc_candidates_reads_probes_random_share_imitate_planner_final_mirror": Row(
        "PCRN-FC+ choosing among the greedy planner's candidate probes from PCRN's state and what each candidate read "
        "so far, never one twice, copying the planner for 8000 steps, then the hybrid rule + wide touch set with a "
        "quarter of the episodes probed with random candidates for the classifiers, temperature falling to a tenth, "
        f"16000 steps, learning rate falling to 5%, {FINAL_TOUCH_SET}, both touch sets reading an episode and its "
        "mirror image across the line alike (beyond the paper)"),
    "pcrn_fc_candidates_along_line_imitate_planner_final_mirror": Row(
        "PCRN-FC+ choosing among the greedy planner's candidate probes from PCRN's state and what each candidate read "
        "so far, the same function of the readings at every place along the line, never one twice, copying the "
        "planner for 8000 steps, then the hybrid rule + wide touch set, temperature falling to a tenth, 16000 steps, "
        f"learning rate falling to 5%, {FINAL_TOUCH_SET}, both touch sets reading an episode and its mirror image "
        "across the line alike (beyond the paper)"),
    "pcrn_fc_candidates_readings_only_imitate_planner_final_mirror": Row(
        "PCRN-FC+ choosing among the greedy planner's candidate probes from what each candidate read so far alone (not "
        "PCRN's state), never one twice, copying the planner for 8000 steps, then the hybrid rule + wide touch set, "
        f"temperature falling to a tenth, 16000 steps, learning rate falling to 5%, {FINAL_TOUCH_SET}, both touch "
        "sets reading an episode and its mirror image across the line alike (beyond the paper)"),
    "pcrn_fc_candidates_readings_only_imitate_planner_final_mirror_library_namer": Row(
        "PCRN-FC+ choosing among the greedy planner's candidate probes from what each candidate read so far alone "
        "(the trained models of the row without the namer), with the greedy planner's namer over a library of training "
        "episodes added to every prediction (beyond the paper)",
        scores="pcrn_fc_candidates_readings_only_imitate_planner_final_mirror"),
    "pcrn_fc_candidates_readings_only_imitate_planner_final_mirror_library_namer65k": Row(
        "PCRN-FC+ choosing among the greedy planner's candidate probes from what each candidate read so far alone "
        "(the trained models of the row without the namer), with the greedy planner's namer over a library of twice as "
        "many training episodes (65536, with their shifts and mirror images) added to every prediction (beyond the "
        "paper)",
        scores="pcrn_fc_candidates_readings_only_imitate_planner_final_mirror"),
    "pcrn_fc_candidates_readings_only_imitate_planner65k_final_mirror": Row(
        "PCRN-FC+ choosing among the greedy planner's candidate probes from what each candidate read so far alone (not "
        "PCRN's state), never one twice, copying the planner over twice as many training episodes (65536) for 8000 "
        "steps, then the hybrid rule + wide touch set, temperature falling to a tenth, 16000 steps, learning rate "
        f"falling to 5%, {FINAL_TOUCH_SET}, both touch sets reading an episode and its mirror image across the line "
        "alike (beyond the paper)"),
    "pcrn_fc_candidates_readings_only_imitate_planner65k_final_mirror_library_namer": Row(
        "PCRN-FC+ choosing among the greedy planner's candidate probes from what each candidate read so far alone, "
        "copying the planner over 65536 training episodes (the trained models of the row without the namer), with its "
        "namer over the same library added to every prediction (beyond the paper)",
        scores="pcrn_fc_candidates_readings_only_imitate_planner65k_final_mirror"),
    "pcrn_fc_candidates_readings_only_imitate_only_planner65k_final_mirror_library_namer": Row(
        "PCRN-FC+ choosing among the greedy planner's candidate probes from what each candidate read so far alone, "
        "never one twice, copying the planner over 65536 training episodes for 8000 steps and nothing after, wide "
        f"touch set, learning rate falling to 5%, {FINAL_TOUCH_SET}, both touch sets reading an episode and its mirror "
        "image across the line alike, with the planner's namer added to every prediction (beyond the paper)"),
    "pcrn_fc_candidates_readings_only_belief_imitate_only_planner65k_final_mirror_library_namer": Row(
        "PCRN-FC+ choosing among the greedy planner's candidate probes from what each candidate read so far and what "
        "the planner's namer believes of them (class, where the object lies), never one twice, copying the planner "
        "over 65536 training episodes for 8000 steps and nothing after, wide touch set, learning rate falling to 5%, "
        f"{FINAL_TOUCH_SET}, both touch sets reading an episode and its mirror image across the line alike, with the "
        "namer added to every prediction (beyond the paper)"),
    "pcrn_fc_candidates_readings_only_along_line_classifier_imitate_planner_final_mirror": Row(
        "PCRN-FC+ choosing among the greedy planner's candidate probes from what each candidate read so far alone (not "
        "PCRN's state), never one twice, copying the planner for 8000 steps, then the hybrid rule + wide touch set + "
        "a classifier of the readings by candidate the same along the line, temperature falling to a tenth, 16000 "
        f"steps, learning rate falling to 5%, {FINAL_TOUCH_SET}, the touch sets and that classifier reading an "
        "episode and its mirror image across the line alike (beyond the paper)"),
    "pcrn_fc_candidates_imitate_planner_final_mirror_encoder": Row(
        "PCRN-FC+ choosing among the greedy planner's candidate probes, copying the planner for 8000 steps, then the "
        f"hybrid rule + wide touch set, temperature falling to a tenth, 16000 steps, learning rate falling to 5%, "
        f"{FINAL_TOUCH_SET}, the touch sets, the encoder and the choice reading an episode and its mirror image across "
        "the line alike (beyond the paper)"),
    "pcrn_fc_coarse_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay": Row(
        "PCRN-FC+ from the coarse-first scan + wide touch set, std shrinking to a tenth, 16000 steps with the policy "
        "from step 8000, policy starting exactly on the scan and held near it, learning rate falling to 5% (beyond "
        "the paper)"),
    "pcrn_fc_centre_touchset_warmup_wide_std_decay_exact_anchor_ema": Row(
        "PCRN-FC+ from the centre-out scan + wide touch set, policy from step 4000, std shrinking to a tenth, "
        "policy starting exactly on the scan and held near it, moving average of the weights (beyond the paper)"),
    "pcrn_fc_centre_touchset_warmup_wide_std_decay_long_exact_anchor_lr_decay_ema": Row(
        "PCRN-FC+ from the centre-out scan + wide touch set, std shrinking to a tenth, 16000 steps with the policy "
        "from step 8000, policy starting exactly on the scan and held near it, learning rate falling to 5%, moving "
        "average of the weights (beyond the paper)"),
}


def config_of(row: str) -> str:
    """The config that trains `row` (the script that plans, for a planner row), relative to the repository root."""
    return "scripts/plan.py" if ROWS[row].planner else f"configs/{row}.yaml"


# Table 1 of Riou et al. (ICASSP 2021): accuracy after k probes, 4 objects, held-out poses (no entry for k=1).
PAPER = {
    "LSTM": {2: 0.308, 3: 0.304, 4: 0.289, 5: 0.298, 6: 0.331, 7: 0.526, 8: 0.577, 9: 0.703, 10: 0.723},
    "PCRN-N-class": {2: 0.205, 3: 0.112, 4: 0.222, 5: 0.286, 6: 0.345, 7: 0.429, 8: 0.506, 9: 0.695, 10: 0.843},
    "PCRN-FC": {2: 0.416, 3: 0.505, 4: 0.576, 5: 0.615, 6: 0.649, 7: 0.670, 8: 0.687, 9: 0.710, 10: 0.796},
}


def run_name(row: str, seed: int) -> str:
    return f"{row}-seed{seed}"


# -- one run (child process) -------------------------------------------------------------------------------
def train_and_test(row: str, seed: int, runs_dir: Path, out_dir: Path, steps: int | None, jobs: int,
                   test_episodes: int = TEST_EPISODES) -> None:
    """Train one (row, seed) with the paper protocol, resuming from its last checkpoint; score the checkpoint
    that was best on val on the test set; write the run JSON atomically (its presence marks the run done)."""
    from hg.lightning.experiment import fit_and_test

    code_commit = commit()  # the code this run trains with, read before it starts
    name = run_name(row, seed)
    source, checkpoint = ROWS[row].scores, None
    if source:
        source_run = out_dir / "runs" / f"{run_name(source, seed)}.json"
        if not source_run.is_file():
            raise FileNotFoundError(f"{source_run}: row {row} scores the checkpoints of row {source}; run its seed "
                                    f"{seed} first")
        checkpoint = ROOT / json.loads(source_run.read_text())["best_checkpoint"]
    if ROWS[row].planner:
        facts = plan_and_test(ROWS[row].planner, seed, test_episodes, planned=ROWS[row].planned)
    else:
        facts = fit_and_test(ROOT / config_of(row), seed, runs_dir / name, eval_seed=EVAL_SEED,
                             test_episodes=test_episodes, steps=steps, checkpoint=checkpoint)
    if source:
        facts["scores_checkpoint_of"] = source
    result = {"row": row, "label": ROWS[row].label, "config": config_of(row), "seed": seed, **facts,
              "parallel_jobs": jobs, "commit": code_commit, "hardware": hardware()}
    write_atomic(out_dir / "runs" / f"{name}.json", json.dumps(result, indent=1) + "\n")


def plan_and_test(library: tuple[str, ...], seed: int, test_episodes: int, extra: tuple[str, ...] = (),
                  planned: str = "planner") -> dict:
    """A planner row's run: scripts/plan.py (hg.planner) with its `library` (drawn with `seed`) on the test episodes
    every row meets, in arm mode (`extra`: more of its arguments, e.g. --noise); the facts fit_and_test returns for
    its result `planned`, with the script's wall time (library and planning) as the training time. Nothing is
    learned, so there is no checkpoint and no validation score."""
    from hg.lightning.data import ProbeDataModule
    from hg.lightning.experiment import test_fingerprint

    command = ["scripts/plan.py", *library, "--split", "test", "--episodes", str(test_episodes),
               "--table-episodes", "--mode", "arm", "--seed", str(seed), *extra]
    start = time.time()
    proc = subprocess.run([sys.executable, *command], capture_output=True, text=True, cwd=ROOT)
    if proc.returncode:
        raise RuntimeError(f"{' '.join(command)} failed (exit {proc.returncode}): {proc.stderr[-2000:]}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])[planned]
    data = ProbeDataModule(test_episodes=test_episodes, eval_seed=EVAL_SEED)
    return {"command": " ".join(command), "max_steps": 0, "resumed_from_step": 0, "accuracy": result["accuracy"],
            "accuracy_mean_action": None, "best_val_acc": None, "best_checkpoint": None,
            "train_wall_s": round(time.time() - start, 1), "test_wall_s": 0.0, "test_episodes": test_episodes,
            "test_fingerprint": test_fingerprint(data), "torch_threads": 1}


# -- merge ------------------------------------------------------------------------------------------------
def load_runs(out_dir: Path) -> dict[str, list[dict]]:
    runs: dict[str, list[dict]] = {}
    for path in sorted((out_dir / "runs").glob("*.json")):
        try:
            run = json.loads(path.read_text())
            runs.setdefault(run["row"], []).append(run)
        except (json.JSONDecodeError, KeyError) as exc:
            raise ValueError(f"{path}: not a run result of this script ({exc})") from exc
    fingerprints = {(r["test_episodes"], r["test_fingerprint"]) for rs in runs.values() for r in rs}
    if len(fingerprints) > 1:
        raise ValueError(f"{out_dir / 'runs'}: runs were scored on different test episodes ({sorted(fingerprints)})")
    return {row: sorted(runs[row], key=lambda r: r["seed"]) for row in ROWS if row in runs}


def summarise(runs: dict[str, list[dict]]) -> dict[str, dict]:
    """Mean and std (over seeds, ddof=1; 0 for one seed) of the accuracy after each probe, per row."""
    table = {}
    for row, rs in runs.items():
        # a planner row names its whole command (the library's arguments), a trained row its config
        entry = {"label": ROWS[row].label, "config": rs[0].get("command", config_of(row)), "seeds": [r["seed"] for r in rs]}
        for key in ("accuracy", "accuracy_mean_action", "accuracy_namer_alone"):  # the last: a row with a namer
            if all(r.get(key) is not None for r in rs):
                values = np.array([r[key] for r in rs])
                std = values.std(0, ddof=1) if len(rs) > 1 else np.zeros(values.shape[1])
                entry[key], entry[f"{key}_std"] = values.mean(0).round(4).tolist(), std.round(4).tolist()
        if all(r.get("best_val_acc") is not None for r in rs):
            entry["best_val_acc"] = round(float(np.mean([r["best_val_acc"] for r in rs])), 4)
        entry["train_wall_s"] = [r["train_wall_s"] for r in rs]
        entry["commits"] = sorted({r["commit"] for r in rs})
        entry["hardware"] = sorted({r["hardware"] for r in rs})
        table[row] = entry
    return table


def best_pcrn(table: dict[str, dict]) -> str | None:
    """The learned PCRN row with the highest mean validation accuracy after 10 probes: chosen on val, never on
    the test episodes the table reports, and among the rows that have all their seeds when any has (one lucky
    seed must not outrank a mean over three)."""
    pcrn = [row for row in table if ROWS[row].learned and ROWS[row].encoder == "pcrn"]
    complete = [row for row in pcrn if len(table[row]["seeds"]) >= len(SEEDS)]
    return max(complete or pcrn, key=lambda row: table[row].get("best_val_acc", -1.0)) if pcrn else None


def targets(table: dict[str, dict]) -> list[str]:
    """The issue's targets, each as a line saying met / not met and by how much."""
    lines = []
    best = best_pcrn(table)
    if best:
        acc = table[best]["accuracy"]
        paper_best = {k: max(col[k] for col in PAPER.values()) for k in range(2, 11)}
        among = f" among the rows with all {len(SEEDS)} seeds" if len(table[best]["seeds"]) >= len(SEEDS) else ""
        lines.append(f"- Best PCRN variant (highest mean validation accuracy after 10 probes{among}, "
                     f"{table[best].get('best_val_acc', float('nan')):.3f}): {table[best]['label']}.")
        for k, goal in ((10, 0.95), (5, 0.85)):
            lines.append(f"- After {k} probes >= {goal}: {'met' if acc[k - 1] >= goal else 'not met'} "
                         f"({acc[k - 1]:.3f}, {acc[k - 1] - goal:+.3f}).")
        short = {k: acc[k - 1] - paper_best[k] for k in paper_best if acc[k - 1] < paper_best[k]}
        lines.append("- At every probe count at least the paper's best entry: " + (
            "met." if not short else "not met at " + ", ".join(f"{k} probes ({d:+.3f})" for k, d in short.items()) + "."))
        for other in (row for row in table if not ROWS[row].learned and not ROWS[row].planner):  # same classifier
            gap = acc[-1] - table[other]["accuracy"][-1]
            lines.append(f"- Beats {table[other]['label']} by >= 0.15 after 10 probes: "
                         f"{'met' if gap >= 0.15 else 'not met'} ({gap:+.3f}).")
        for other in (row for row in table if ROWS[row].namer_of):  # the same namer reading probes placed by no one
            label, namer_of = table[other]["label"], ROWS[other].namer_of
            if namer_of != best or "accuracy_namer_alone" not in table[best]:
                lines.append(f"- Beats {label} by >= 0.15 after 10 probes: not compared (named by the namer of "
                             f"{namer_of}, not the best variant's).")
                continue
            alone = table[best]["accuracy_namer_alone"][-1]
            gap = alone - table[other]["accuracy"][-1]
            lines.append(f"- Beats {label} by >= 0.15 after 10 probes, the same namer alone reading both: "
                         f"{'met' if gap >= 0.15 else 'not met'} ({gap:+.3f}; the best variant's namer alone "
                         f"{alone:.3f}, with its classifier {acc[-1]:.3f}).")
        if "lstm" in table:
            lost = [k for k in range(3, 11) if acc[k - 1] <= table["lstm"]["accuracy"][k - 1]]
            lines.append("- Beats the LSTM at every probe count from 3 on: " + (
                "met." if not lost else f"not met at {lost}."))
    return lines


def summary(table: dict[str, dict]) -> list[str]:
    """One line per row, for reading the rows against each other: the full per-probe tables follow it."""
    paper = {ROWS[r].paper: PAPER[ROWS[r].paper][10] for r in table if ROWS[r].paper}

    def cell(entry: dict, key: str, k: int) -> str:
        if key not in entry:
            return ""
        mean, std = entry[key][k - 1], entry[f"{key}_std"][k - 1]
        return f"{mean:.3f}" if len(entry["seeds"]) == 1 else f"{mean:.3f} +- {std:.3f}"

    lines = ["| row | seeds | after 1 | after 3 | after 5 | after 10 | after 10, mean action | validation, after 10 "
             "| paper, after 10 |", "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r, entry in table.items():
        val = entry.get("best_val_acc")
        lines.append(f"| {entry['label']} | {len(entry['seeds'])} | " + " | ".join(
            cell(entry, "accuracy", k) for k in (1, 3, 5)) + f" | **{cell(entry, 'accuracy', 10)}** | "
            f"{cell(entry, 'accuracy_mean_action', 10)} | {'' if val is None else f'{val:.3f}'} | "
            f"{paper.get(ROWS[r].paper, '')} |")
    return lines


def markdown(table: dict[str, dict], runs: dict[str, list[dict]], merged_at: str) -> str:
    n = len(next(iter(table.values()))["accuracy"])
    rows, first = list(table), next(iter(runs.values()))[0]
    lines = ["# Table 1, reproduced and compared",
             "",
             f"Accuracy after each probe on the same {first['test_episodes']} held-out test episodes (pose regions never used in "
             "training), single stochastic rollout, mean +- std over training seeds; each model is the checkpoint "
             "best on the validation episodes (a third, separate pose region). The paper's figures (Riou et al., "
             "ICASSP 2021, Table 1) stand beside ours in the `paper` columns; they come from the authors' own "
             "simulator, so they are a yardstick, not the same experiment.",
             "",
             "Produced by `.venv/bin/python scripts/reproduce_table1.py` (paper protocol: 8000 steps, batch 64, "
             "10 probes, arm mode, hg4; the configs are named below). Merged at commit "
             f"`{merged_at}`; each row's runs were made at the commits listed with it.",
             "",
             "In short (the tables after each probe follow; chance is 0.25):",
             "",
             *summary(table),
             "",
             "## After each probe",
             "",
             "| probes | " + " | ".join(table[r]["label"] for r in rows) + " | " + " | ".join(
                 f"paper {c}" for c in PAPER) + " |",
             "|---:|" + "---:|" * (len(rows) + len(PAPER))]
    for k in range(n):
        cells = [f"{table[r]['accuracy'][k]:.3f} +- {table[r]['accuracy_std'][k]:.3f}" for r in rows]
        cells += [f"{PAPER[c][k + 1]:.3f}" if k + 1 in PAPER[c] else "" for c in PAPER]
        lines.append(f"| {k + 1} | " + " | ".join(cells) + " |")
    lines += ["", "![accuracy after each probe](table1.png)", "",
              "Learned policies, mean-action rollout (the Gaussian's mean instead of a sample), same episodes:", "",
              "| probes | " + " | ".join(table[r]["label"] for r in rows if "accuracy_mean_action" in table[r]) + " |",
              "|---:|" + "---:|" * sum("accuracy_mean_action" in table[r] for r in rows)]
    for k in range(n):
        lines.append(f"| {k + 1} | " + " | ".join(
            f"{table[r]['accuracy_mean_action'][k]:.3f} +- {table[r]['accuracy_mean_action_std'][k]:.3f}"
            for r in rows if "accuracy_mean_action" in table[r]) + " |")
    lines += ["", "## Runs", "",
              "| row | config | seeds | training wall time per seed (s) | jobs in parallel | commits | hardware |",
              "|---|---|---|---|---|---|---|"]
    for r in rows:
        jobs = sorted({run["parallel_jobs"] for run in runs[r]})
        lines.append(f"| {table[r]['label']} | `{table[r]['config']}` | {table[r]['seeds']} | "
                     f"{', '.join(f'{s:.0f}' for s in table[r]['train_wall_s'])} | {jobs} | "
                     f"{', '.join(f'`{c}`' for c in table[r]['commits'])} | "
                     f"{'; '.join(table[r]['hardware'])} |")
    lines += ["", "With two jobs in parallel each trains on one torch thread.",
              "A run resumed after an interruption counts every attempt's training time up to its last checkpoint "
              "(`hg.lightning.callbacks.TrainingClock`, in the checkpoints since 2026-12-05); one resumed before "
              "that counts only its last attempt (`resumed_from_step` in its JSON).",
              "", "## Targets (issue #4)", "", *targets(table), ""]
    return "\n".join(lines)


def merge(out_dir: Path) -> dict:
    from hg.lightning.callbacks import accuracy_plot

    runs = load_runs(out_dir)
    if not runs:
        raise SystemExit(f"{out_dir / 'runs'}: no finished runs to merge")
    table = summarise(runs)
    merged_at = commit(paths=())
    write_atomic(out_dir / "table1.json", json.dumps({"commit": merged_at,
                                                      "test_episodes": next(iter(runs.values()))[0]["test_episodes"],
                                                      "test_fingerprint": next(iter(runs.values()))[0]["test_fingerprint"],
                                                      "best_pcrn": best_pcrn(table), "rows": table, "paper": PAPER},
                                                     indent=1) + "\n")
    write_atomic(out_dir / "table1.md", markdown(table, runs, merged_at))
    write_atomic(out_dir / "table1.png", accuracy_plot(
        {f"{t['label']} (n={len(t['seeds'])})": t["accuracy"] for t in table.values()},
        reference={f"paper {c}": col for c, col in PAPER.items()}))
    return {"commit": merged_at, **{row: t["accuracy"] for row, t in table.items()}}


# -- driver -----------------------------------------------------------------------------------------------
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    parser.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    parser.add_argument("--jobs", type=int, default=1,
                        help="runs trained at once")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch threads per run (default: cores / jobs); beside other work on the machine use 1, "
                             "since a run on 2 threads sharing a core with another process crawls (0.25 steps/s against 5.8 "
                             "on 1 thread, measured)")
    parser.add_argument("--steps", type=int, default=None, help="override max_steps (smoke tests only)")
    parser.add_argument("--test-episodes", type=int, default=TEST_EPISODES, help="test set size (smoke tests only)")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    parser.add_argument("--runs-dir", type=Path, default=ROOT / "runs" / "table1", help="checkpoints and wandb runs")
    parser.add_argument("--merge-only", action="store_true")
    parser.add_argument("--one", nargs=2, metavar=("ROW", "SEED"), help=argparse.SUPPRESS)  # the child's job
    args = parser.parse_args()
    if args.threads is not None and args.threads < 1:
        parser.error(f"--threads {args.threads}: must be >= 1")
    if args.one:
        train_and_test(args.one[0], int(args.one[1]), args.runs_dir, args.out, args.steps, args.jobs, args.test_episodes)
        return
    if not args.merge_only:
        todo = [(row, seed) for seed in args.seeds for row in args.rows  # seed-major: every row gets a seed early
                if not (args.out / "runs" / f"{run_name(row, seed)}.json").is_file()]
        print(f"{len(todo)} runs to train: {', '.join(run_name(*t) for t in todo) or 'none'}", flush=True)
        threads = args.threads or max(1, (os.cpu_count() or 1) // args.jobs)

        def launch(job: tuple[str, int]) -> int:
            row, seed = job
            log = args.runs_dir / run_name(row, seed) / "log.txt"
            log.parent.mkdir(parents=True, exist_ok=True)
            command = [sys.executable, __file__, "--one", row, str(seed), "--out", str(args.out),
                       "--runs-dir", str(args.runs_dir), "--jobs", str(args.jobs), "--test-episodes", str(args.test_episodes)]
            command += ["--steps", str(args.steps)] if args.steps is not None else []
            env = {**os.environ, "OMP_NUM_THREADS": str(threads), "WANDB_MODE": os.environ.get("WANDB_MODE", "offline")}
            start = time.time()
            with open(log, "a") as stream:
                code = subprocess.run(command, stdout=stream, stderr=subprocess.STDOUT, env=env, cwd=ROOT).returncode
            # a child stopped by SIGTERM leaves Lightning's fit with exit 0 and no result: not done
            written = (args.out / "runs" / f"{run_name(row, seed)}.json").is_file()
            state = ("done" if written else f"stopped before writing its result, see {log}") if code == 0 else \
                f"FAILED (exit {code}), see {log}"
            print(f"{run_name(row, seed)}: {state} in {time.time() - start:.0f} s", flush=True)
            return code if code or written else 1

        failed = 0
        for scoring in (False, True):  # the rows that score other rows' checkpoints after those rows
            with ThreadPoolExecutor(max(1, args.jobs)) as pool:
                failed += sum(code != 0 for code in pool.map(launch, [t for t in todo
                                                                       if bool(ROWS[t[0]].scores) == scoring]))
        if failed:
            print(f"{failed} runs failed; merging the finished ones", flush=True)
    print(json.dumps(merge(args.out)))


if __name__ == "__main__":
    try:
        main()
    except (ValueError, FileNotFoundError) as exc:  # bad inputs end in one line naming the file
        sys.exit(f"reproduce_table1: error: {exc}")
