"""The Table 1 and noise scripts: real (tiny) runs, resuming instead of recomputing, and the merge's checks."""
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from hg.sim import ProbeSimulator, candidate_requests
from hg.sim.library import MISS, library_readings, readings

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "WANDB_MODE": "disabled", "OMP_NUM_THREADS": "1"}


def script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def run(name: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "scripts" / f"{name}.py"), *args], capture_output=True,
                          text=True, env=ENV, cwd=ROOT, timeout=600)


def fake_run(out: Path, row: str, seed: int, accuracy: list[float], fingerprint: str = "abc",
             val: float = 0.5, **facts) -> None:
    learned = row not in ("random", "line_scan", "centre_scan")
    record = {"row": row, "label": row, "config": f"configs/{row}.yaml", "seed": seed, "accuracy": accuracy,
              "accuracy_mean_action": accuracy if learned else None, "best_val_acc": val, "train_wall_s": 1.0,
              "parallel_jobs": 1,
              "test_episodes": 2048, "test_fingerprint": fingerprint, "commit": "abc1234", "hardware": "cpu", **facts}
    (out / "runs").mkdir(parents=True, exist_ok=True)
    (out / "runs" / f"{row}-seed{seed}.json").write_text(json.dumps(record))


def test_table_merge_means_stds_paper_columns_and_targets(tmp_path):
    table1 = script("reproduce_table1")
    fake_run(tmp_path, "pcrn_fc", 0, [0.5] * 9 + [0.9])
    fake_run(tmp_path, "pcrn_fc", 1, [0.7] * 9 + [1.0])
    fake_run(tmp_path, "random", 0, [0.4] * 10)
    fake_run(tmp_path, "lstm", 0, [0.6] * 10)
    summary = table1.merge(tmp_path)
    assert summary["pcrn_fc"][-1] == pytest.approx(0.95) and summary["random"][0] == pytest.approx(0.4)
    saved = json.loads((tmp_path / "table1.json").read_text())
    assert saved["rows"]["pcrn_fc"]["accuracy_std"][0] == pytest.approx(0.1414, abs=1e-4)  # ddof=1 over 2 seeds
    assert saved["rows"]["pcrn_fc"]["seeds"] == [0, 1] and saved["paper"]["PCRN-FC"]["10"] == 0.796
    text = (tmp_path / "table1.md").read_text()
    assert "| 10 | 0.950 +- 0.071 | 0.600 +- 0.000 | 0.400 +- 0.000 | 0.723 | 0.843 | 0.796 |" in text
    # the one-line summary: seeds, stochastic and mean-action accuracy, validation, the paper's figure; no std of 1 seed
    assert ("| PCRN-FC | 2 | 0.600 +- 0.141 | 0.600 +- 0.141 | 0.600 +- 0.141 | **0.950 +- 0.071** | 0.950 +- 0.071 "
            "| 0.500 | 0.796 |") in text
    assert "| random probes + PCRN-FC | 1 | 0.400 | 0.400 | 0.400 | **0.400** |  | 0.500 |  |" in text
    assert "After 10 probes >= 0.95: met (0.950, +0.000)" in text
    assert "After 5 probes >= 0.85: not met (0.600, -0.250)" in text
    assert "Beats random + PCRN-FC" not in text and "by >= 0.15 after 10 probes: met (+0.550)" in text
    assert "Beats the LSTM at every probe count from 3 on: not met at [3, 4, 5, 6, 7, 8, 9]." in text
    assert (tmp_path / "table1.png").read_bytes()[:4] == b"\x89PNG"


def test_every_row_is_trained_by_its_shipped_config():
    table1 = script("reproduce_table1")
    missing = [row for row in table1.ROWS if not (table1.ROOT / table1.config_of(row)).is_file()]
    assert not missing and len(table1.ROWS) >= 5


def test_a_row_scoring_another_row_s_checkpoints_needs_that_row_s_run_first(tmp_path):
    table1 = script("reproduce_table1")
    scoring = [row for row, spec in table1.ROWS.items() if spec.scores]
    assert scoring and all(table1.ROWS[row].scores in table1.ROWS for row in scoring)
    with pytest.raises(FileNotFoundError, match=f"row {scoring[0]} scores the checkpoints of row .*; run its seed 0 "
                                                "first"):
        table1.train_and_test(scoring[0], 0, tmp_path / "ckpt", tmp_path, None, 1)


def test_planner_row_plans_on_the_table_s_test_episodes_and_merges_beside_the_learned_rows(tmp_path):
    table1 = script("reproduce_table1")
    tiny = ("--library-split", "train", "--library", "128")  # the planner row's own library is minutes to read
    table1.ROWS["tiny_planner"] = table1.Row("tiny planner", learned=False, planner=tiny)
    table1.train_and_test("tiny_planner", 0, tmp_path / "ckpt", tmp_path, None, 1, test_episodes=16)
    record = json.loads((tmp_path / "runs" / "tiny_planner-seed0.json").read_text())
    assert record["command"].startswith("scripts/plan.py --library-split train --library 128 --split test")
    assert len(record["accuracy"]) == 10 and all(0 <= a <= 1 for a in record["accuracy"])
    assert record["accuracy_mean_action"] is None and record["config"] == "scripts/plan.py"
    fake_run(tmp_path, "pcrn_fc", 0, [0.5] * 10, fingerprint=record["test_fingerprint"])
    fake_run(tmp_path, "random", 0, [0.3] * 10, fingerprint=record["test_fingerprint"])
    record["test_episodes"] = 2048  # as fake_run's
    (tmp_path / "runs" / "tiny_planner-seed0.json").write_text(json.dumps(record))
    table1.merge(tmp_path)
    text = (tmp_path / "table1.md").read_text()
    assert "| tiny planner | 1 |" in text and "Beats random probes + PCRN-FC by >= 0.15 after 10 probes: met (+0.200)" in text
    assert "| tiny planner | `scripts/plan.py --library-split train --library 128 --split test" in text
    assert "Beats tiny planner" not in text  # the 0.15 targets compare policies feeding one classifier


def test_probes_placed_by_no_one_are_set_against_the_best_variant_s_namer_alone(tmp_path):
    """A row of random candidates named by the best variant's namer: the 0.15 margin is read with that namer alone on
    both sides (the same classifier), not with the variant's classifier added; another row's namer is not compared."""
    table1 = script("reproduce_table1")
    best, random_named = table1.NAMER_65K, "random_candidates_namer65k"
    assert table1.ROWS[random_named].namer_of == best and table1.ROWS[random_named].planned == "random"
    assert "--random" in table1.ROWS[random_named].planner and "--fixed" in table1.ROWS["candidate_scan_namer65k"].planner
    fake_run(tmp_path, best, 0, [0.95] * 10, val=0.9, accuracy_namer_alone=[0.9] * 10)
    fake_run(tmp_path, random_named, 0, [0.8] * 10, val=None)
    fake_run(tmp_path, "random", 0, [0.4] * 10)
    table1.ROWS["other_namer_scan"] = table1.Row("other namer's scan", learned=False, planner=("--fixed",),
                                                 planned="fixed", namer_of="pcrn_fc")
    fake_run(tmp_path, "other_namer_scan", 0, [0.5] * 10, val=None)
    try:
        table1.merge(tmp_path)
    finally:
        del table1.ROWS["other_namer_scan"]
    saved = json.loads((tmp_path / "table1.json").read_text())["rows"]
    assert saved[best]["accuracy_namer_alone"] == [0.9] * 10 and "accuracy_namer_alone" not in saved["random"]
    text = (tmp_path / "table1.md").read_text()
    label = table1.ROWS[random_named].label
    assert (f"Beats {label} by >= 0.15 after 10 probes, the same namer alone reading both: not met (+0.100; the best "
            "variant's namer alone 0.900, with its classifier 0.950).") in text
    assert "Beats random probes + PCRN-FC by >= 0.15 after 10 probes: met (+0.550)." in text
    assert f"Beats other namer's scan by >= 0.15 after 10 probes: not compared (named by the namer of pcrn_fc" in text


def test_best_pcrn_variant_is_chosen_on_validation_not_test(tmp_path):
    table1 = script("reproduce_table1")
    fake_run(tmp_path, "pcrn_fc", 0, [0.9] * 10, val=0.6)  # best on test, worse on val
    fake_run(tmp_path, "pcrn_fc_plus", 0, [0.7] * 10, val=0.8)
    fake_run(tmp_path, "lstm", 0, [0.95] * 10, val=0.9)  # not a PCRN variant
    fake_run(tmp_path, "centre_scan", 0, [0.6] * 10, val=0.95)  # not learned
    table1.merge(tmp_path)
    assert json.loads((tmp_path / "table1.json").read_text())["best_pcrn"] == "pcrn_fc_plus"
    text = (tmp_path / "table1.md").read_text()
    assert "(highest mean validation accuracy after 10 probes, 0.800): PCRN-FC+ (beyond the paper)." in text
    assert "after 10 probes: not met (+0.100)." in text  # against the centre-out scan, a fixed policy
    for seed in (1, 2):  # once a row has its three seeds, a row with one seed cannot outrank it
        fake_run(tmp_path, "pcrn_fc", seed, [0.9] * 10, val=0.6)
    table1.merge(tmp_path)
    assert json.loads((tmp_path / "table1.json").read_text())["best_pcrn"] == "pcrn_fc"
    assert ("(highest mean validation accuracy after 10 probes among the rows with all 3 seeds, 0.600): PCRN-FC."
            in (tmp_path / "table1.md").read_text())


def test_table_merge_refuses_runs_scored_on_different_test_episodes(tmp_path):
    fake_run(tmp_path, "pcrn_fc", 0, [0.5] * 10, fingerprint="aaa")
    fake_run(tmp_path, "random", 0, [0.4] * 10, fingerprint="bbb")
    result = run("reproduce_table1", "--merge-only", "--out", str(tmp_path))
    assert result.returncode != 0
    assert "different test episodes" in result.stderr and str(tmp_path / "runs") in result.stderr
    assert not (tmp_path / "table1.md").exists()  # nothing half-written


def test_table_row_trains_once_is_reused_and_feeds_the_noise_study(tmp_path):
    args = ["--rows", "pcrn_fc", "--seeds", "0", "--steps", "2", "--test-episodes", "64", "--out", str(tmp_path),
            "--runs-dir", str(tmp_path / "ckpt"), "--threads", "1"]
    assert run("reproduce_table1", *args[:-1], "0").returncode != 0  # --threads 0 refused before anything runs
    assert not (tmp_path / "runs").exists()
    first = run("reproduce_table1", *args)
    assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-2000:]
    assert "pcrn_fc-seed0: done in" in first.stdout  # its result written (a child stopped before that is not done)
    record = json.loads((tmp_path / "runs" / "pcrn_fc-seed0.json").read_text())
    assert len(record["accuracy"]) == len(record["accuracy_mean_action"]) == 10
    assert all(0 <= a <= 1 for a in record["accuracy"])
    assert record["test_episodes"] == 64 and record["max_steps"] == 2
    assert record["torch_threads"] == 1  # as asked, not cores / jobs
    assert (tmp_path / "ckpt" / "pcrn_fc-seed0" / "checkpoints" / "last.ckpt").is_file()
    second = run("reproduce_table1", *args)
    assert second.returncode == 0 and "0 runs to train" in second.stdout
    assert json.loads(second.stdout.strip().splitlines()[-1])["pcrn_fc"] == record["accuracy"]
    # our model under sensor noise: the table's checkpoint, its test episodes, each reading corrupted
    ours = run("reproduce_noise", "--models", "ours", "--rates", "0", "0.5", "--out", str(tmp_path))
    assert ours.returncode == 0, ours.stderr[-2000:]
    clean, noisy = (json.loads((tmp_path / "noise_runs" / f"ours-pcrn_fc-rate{r}-seed0.json").read_text())
                    for r in ("00", "50"))
    assert clean["accuracy"] == record["accuracy"][-1]  # rate 0 is the table's own test
    assert clean["checkpoint"] == noisy["checkpoint"] == record["best_checkpoint"]
    # results of a row that is no longer the best stay on disk but out of the merge
    stale = {**clean, "row": "pcrn_nclass", "accuracy": 0.99}
    (tmp_path / "noise_runs" / "ours-pcrn_nclass-rate00-seed0.json").write_text(json.dumps(stale))
    again = run("reproduce_noise", "--models", "ours", "--rates", "0", "0.5", "--out", str(tmp_path))
    assert again.returncode == 0 and json.loads(again.stdout.strip().splitlines()[-1])["ours"][0] == clean["accuracy"]
    # ours trained at the rate: rate 0 is the table's run, others train the row's config with the noise on
    trained = run("reproduce_noise", "--models", "ours_trained", "--rates", "0", "0.5", "--seeds", "0",
                  "--ours-steps", "2", "--out", str(tmp_path), "--runs-dir", str(tmp_path / "noise_ckpt"))
    assert trained.returncode == 0, trained.stderr[-2000:]
    clean, noisy = (json.loads((tmp_path / "noise_runs" / f"ours_trained-pcrn_fc-rate{r}-seed0.json").read_text())
                    for r in ("00", "50"))
    assert clean["accuracy"] == record["accuracy"][-1] and clean["checkpoint"] == record["best_checkpoint"]
    assert noisy["max_steps"] == 2 and len(noisy["accuracy_per_probe"]) == 10
    saved = torch.load(ROOT / noisy["checkpoint"], map_location="cpu", weights_only=False)
    assert saved["datamodule_hyper_parameters"]["noise"]["miss_prob"] == 0.5  # it trained with the noise on
    merged = json.loads(trained.stdout.strip().splitlines()[-1])
    assert len(merged["ours_trained-pcrn_fc"]) == 2 and merged["ours"][0] == record["accuracy"][-1]
    noise_md = (tmp_path / "noise.md").read_text()
    assert "Ours trained at the rate" in noise_md and "| [0] |" in noise_md  # every rate of it has seed 0 only
    # a record made otherwise (say copying other teachers) is not taken for this run's, nor overwritten
    made = tmp_path / "noise_runs" / "ours_trained-pcrn_fc-rate50-seed0.json"
    made.write_text(json.dumps(noisy | {"command_args": noisy["command_args"] + ["--model.imitate", '["x.npz"]']}))
    other = run("reproduce_noise", "--models", "ours_trained", "--rates", "0.5", "--seeds", "0", "--ours-steps", "2",
                "--out", str(tmp_path), "--runs-dir", str(tmp_path / "noise_ckpt"))
    assert other.returncode != 0 and "ours_trained-pcrn_fc-rate50-seed0.json: made with [" in other.stderr
    assert "x.npz" in json.loads(made.read_text())["command_args"][-1]
    missing = run("reproduce_noise", "--models", "ours_trained", "--rates", "0", "--seeds", "1", "--out", str(tmp_path))
    assert missing.returncode != 0 and "pcrn_fc-seed1.json: no table run" in missing.stderr
    # where the checkpoint's policy probes, beside the fixed scans, on the same episodes
    coverage = run("scan_coverage", "--episodes", "32", "--spans", "0.5", "--leans", "0", "0.4",
                   "--follows", "0", "0.05", "--ckpt", record["best_checkpoint"], "--fit", "32", "--fit-epochs", "1")
    assert coverage.returncode == 0, coverage.stderr[-2000:]
    figures = json.loads(coverage.stdout.strip().splitlines()[-1])
    scans = {f"{order}-span0.5{lean}{follow}" for order in ("sweep", "centre_out") for lean in ("", "-lean0.4")
             for follow in ("", "-follow0.05")}
    assert set(figures) == scans | {record["best_checkpoint"]}
    assert figures["centre_out-span0.5-follow0.05"]["touches"] > figures["centre_out-span0.5"]["touches"]
    sweep, centre = figures["sweep-span0.5"], figures["centre_out-span0.5"]
    assert sweep["touches"] == centre["touches"] > 0 and sweep["tilt_deg"] == 0  # same probes, other order
    fan = figures["centre_out-span0.5-lean0.4"]
    assert fan["tilt_deg"] == pytest.approx(11.31 * 6 / 10, abs=0.1)  # 6 of 10 probes lean 11.3 degrees
    assert centre["towards_object"] is None and 0.3 < fan["towards_object"] < 0.7  # the fan leans both ways
    policy = figures[record["best_checkpoint"]]
    assert 0 <= policy["any_touch"] <= 1 and 0 <= policy["accuracy"] <= 1 and "accuracy" not in centre
    # a classifier trained on each fixed scan's probes; the checkpoint brings its own
    assert all(0 <= figures[s]["fit_accuracy"] <= 1 for s in scans) and "fit_accuracy" not in policy
    assert sweep["fit_accuracy"] == centre["fit_accuracy"]  # the same probes in another order, to a PointNet
    for split in ("by_touches", "by_offset_cm"):
        bins = policy[split].values()
        assert sum(b["share"] for b in bins) == pytest.approx(1, abs=0.01)  # objects lie within 15 cm of the line
        weighted = sum(b["share"] * b["accuracy"] for b in bins if b["accuracy"] is not None)
        assert weighted == pytest.approx(policy["accuracy"], abs=0.01)
    missing = run("scan_coverage", "--ckpt", str(tmp_path / "nope.ckpt"))
    assert missing.returncode != 0 and "nope.ckpt: checkpoint not found" in missing.stderr


def test_noise_baseline_runs_and_merges_and_ours_needs_the_table(tmp_path):
    args = ["--models", "pointnet", "--rates", "0", "0.5", "--seeds", "0", "--steps", "3", "--out", str(tmp_path)]
    first = run("reproduce_noise", *args)
    assert first.returncode == 0, first.stderr[-2000:]
    saved = json.loads((tmp_path / "noise.json").read_text())
    assert saved["models"]["pointnet"]["rates"] == [0.0, 0.5] and len(saved["models"]["pointnet"]["accuracy"]) == 2
    assert (tmp_path / "noise.png").read_bytes()[:4] == b"\x89PNG" and "PointNet" in (tmp_path / "noise.md").read_text()
    second = run("reproduce_noise", *args)
    assert second.returncode == 0 and "accuracy" not in second.stdout.splitlines()[0]  # nothing retrained
    ours = run("reproduce_noise", "--models", "ours", "--out", str(tmp_path))
    assert ours.returncode != 0 and "table1.json" in ours.stderr and "reproduce_table1.py" in ours.stderr


def test_oracle_aimed_scan_passes_under_the_object_centre_or_leans_towards_it():
    import numpy as np

    from hg.sim import PoseRegions, ProbeSimulator, sample_episodes

    coverage = script("scan_coverage")
    sim = ProbeSimulator("hg4", batch_size=16, mode="ideal", seed=0)
    labels, poses = sample_episodes(PoseRegions(sim.scene), "val", 16, 4, np.random.default_rng(0))
    scan = dict(n_probes=4, policy="line_scan", scan_span=0.5, scan_order="centre_out")
    models = {aim: coverage.scan_model(aim, **scan) for aim in ("0", "0.6", "exact")}
    probes = {aim: coverage.policy_probes(model, sim, labels, poses) for aim, model in models.items()}
    plain, fixed, exact = (probes[aim][1] for aim in ("0", "0.6", "exact"))
    pair_then_told = coverage.policy_probes(coverage.scan_model("side", scan_side=0.6, scan_side_first=1.0, **scan),
                                            sim, labels, poses)[1]  # the side-picking scan told the side
    told = {aim: coverage.fit_accuracy(models[aim], sim, PoseRegions(sim.scene), 256, probes[aim][0],
                                       coverage.fit_labels("side", labels, poses, sim.scene), 40, 0,
                                       target="side", probes=2) for aim in ("0", "0.6")}
    sim.close()
    assert told["0.6"] >= 0.9 and told["0"] <= 0.75
    assert isinstance(models["exact"], coverage.OracleAimedScan) and np.allclose(plain[..., :2], 0)
    # each exact probe, entering on the line (x = probe_x), is at the object's centre x at its centre depth
    depth = -poses[:, 2][:, None]
    x_at_depth = sim.scene.probe_x + depth * exact[..., 0] / -exact[..., 2]
    assert np.allclose(x_at_depth, poses[:, 0][:, None], atol=1e-4) and np.allclose(exact[..., 1], 0)
    # a fixed lean: the same tilt for every probe, to the side the object lies on
    side = np.sign(poses[:, 0] - sim.scene.probe_x)[:, None]
    assert (np.sign(fixed[..., 0]) == side).all() and np.allclose(np.abs(fixed[..., 0]), abs(fixed[0, 0, 0]))
    assert (np.sign(pair_then_told[:, :2, 0]) == [1, -1]).all() and (np.sign(pair_then_told[:, 2:, 0]) == side).all()
    bad = run("scan_coverage", "--aims", "left")
    assert bad.returncode != 0 and "--aims: 'left'" in bad.stderr
    offsets = poses[:, 0] - sim.scene.probe_x
    assert coverage.coverage(np.ones((16, 4)), fixed, offsets)["towards_object"] == 1.0
    assert coverage.coverage(np.ones((16, 4)), fixed, -offsets)["towards_object"] == 0.0
    # --fit-target side: probes leaning to the object's side tell it; straight probes cannot (mirror images)
    assert (coverage.fit_labels("side", labels, poses, sim.scene) == (offsets > 0)).all()
    # the side-picking rule without a fit: a lean to the object's side names it, a straight probe names nothing
    told = {aim: coverage.first_touch_side(probes[aim][0][..., 3].numpy(), probes[aim][1], offsets)
            for aim in ("0", "0.6")}
    assert told["0"] == {"share": 0.0, "accuracy": None} and told["0.6"]["share"] > 0.5
    assert told["0.6"]["accuracy"] == 1.0
    assert coverage.first_touch_side(probes["0.6"][0][..., 3].numpy(), -probes["0.6"][1], offsets)["accuracy"] == 0.0
    for bad_args, message in ((["--fit-target", "side", "--fit-net", "touch_set"], "needs --fit-net pointnet"),
                              (["--fit-probes", "0"], "--fit-probes 0")):
        bad = run("scan_coverage", *bad_args)
        assert bad.returncode != 0 and message in bad.stderr


def test_coverage_measures_how_far_a_learned_policy_moved_from_its_prior():
    import numpy as np

    from hg.lightning.module import HapticGlance
    from hg.sim import PoseRegions, ProbeSimulator, sample_episodes

    coverage = script("scan_coverage")
    sim = ProbeSimulator("hg4", batch_size=8, mode="ideal", seed=0)
    labels, poses = sample_episodes(PoseRegions(sim.scene), "val", 8, 4, np.random.default_rng(0))
    model = HapticGlance(width=16, representation=32, hidden=32, prior="line_scan", scan_span=0.5,
                         scan_order="centre_out", prior_exact=True)
    assert coverage.policy_probes(model, sim, labels, poses)[3] == {"py": 0, "ux": 0, "uy": 0, "uz": 0}  # on it
    with torch.no_grad():
        model.location.net[-1].bias[0] += 0.3  # the mean moves Py off the scan, and nothing else
    shift = coverage.policy_probes(model, sim, labels, poses)[3]
    assert shift["py"] > 0.05 and shift["ux"] == shift["uy"] == shift["uz"] == 0
    assert coverage.policy_probes(HapticGlance(policy="line_scan"), sim, labels, poses)[3] is None  # no prior
    sim.close()


def test_noise_table_names_each_rates_seeds_when_they_differ():
    noise = script("reproduce_noise")
    assert noise.seeds_cell({"rates": [0.0, 0.1], "seeds": [[0, 1], [0, 1]]}) == "[0, 1]"
    assert noise.seeds_cell({"rates": [0.0, 0.1], "seeds": [[0], [0, 1, 2]]}) == "0 %: [0]; 10 %: [0, 1, 2]"


def test_knn_ceiling_votes_the_nearest_episodes_and_runs_on_the_scored_split():
    coverage = script("scan_coverage")
    generator = torch.Generator().manual_seed(0)
    library = torch.rand(400, 3, 4, generator=generator)
    labels = (library[:, 0, 2] > 0.5).long()  # the class is the first probe's depth
    queries = torch.rand(200, 3, 4, generator=generator)
    right = coverage.knn_predict(library, labels, queries, k=5, n_classes=2) == (queries[:, 0, 2] > 0.5).long()
    assert right.float().mean() > 0.6  # better than chance although 11 of 12 features are noise
    assert (coverage.knn_predict(library, labels, library, k=1, n_classes=2, chunk=64) == labels).all()  # itself
    near, far = torch.zeros(1, 2, 4), torch.full((1, 2, 4), 0.2)
    tie = coverage.knn_predict(torch.cat([far, near]), torch.tensor([0, 1]), torch.zeros(1, 2, 4), 2, 2)
    assert tie.tolist() == [1]  # one vote each: the nearer neighbour's class
    with pytest.raises(ValueError, match="--fit-k 3: must be in"):
        coverage.knn_predict(library[:2], labels[:2], queries, k=3, n_classes=2)
    knn = run("scan_coverage", "--episodes", "64", "--orders", "centre_out", "--spans", "0.5", "--fit", "256",
              "--fit-net", "knn", "--fit-split", "val", "--fit-k", "4")
    assert knn.returncode == 0, knn.stderr[-2000:]
    assert 0.25 < json.loads(knn.stdout.strip().splitlines()[-1])["centre_out-span0.5"]["fit_accuracy"] <= 1
    bad = run("scan_coverage", "--fit", "8", "--fit-net", "knn", "--fit-k", "9")
    assert bad.returncode != 0 and "--fit-k 9: must be in [1, --fit 8]" in bad.stderr


def test_learned_policy_is_read_against_the_scan_it_started_from():
    import numpy as np

    from hg.lightning.module import HapticGlance
    from hg.sim import PoseRegions, ProbeSimulator, sample_episodes

    coverage = script("scan_coverage")
    sim = ProbeSimulator("hg4", batch_size=64, mode="ideal", seed=0)
    labels, poses = sample_episodes(PoseRegions(sim.scene), "val", 64, 4, np.random.default_rng(0))
    torch.manual_seed(0)
    scan = dict(n_probes=4, scan_span=0.5, scan_order="centre_out")  # straight: no request at the clamp (+-0.9)
    learned = HapticGlance(policy="learned", prior="line_scan", prior_exact=True, **scan).eval()
    points, _, correct, shift = coverage.policy_probes(learned, sim, labels, poses)
    on_scan = coverage.accuracy_on_prior_scan(learned, sim, labels, poses)
    fixed_points = coverage.policy_probes(HapticGlance(policy="line_scan", **scan), sim, labels, poses)[0]
    with torch.no_grad():  # the policy moves off its scan along the line: its probes change, the scan's do not
        learned.location.net[-1].bias[0].add_(0.5)
    moved_points = coverage.policy_probes(learned, sim, labels, poses)[0]
    moved = coverage.accuracy_on_prior_scan(learned, sim, labels, poses)
    sim.close()
    # untrained, exactly on its scan (prior_exact): its probes are the scan's, so it is read as the scan
    assert max(shift.values()) < 1e-5 and torch.allclose(points, fixed_points, atol=1e-5)
    assert on_scan == pytest.approx(float(correct.mean()))
    assert not torch.allclose(moved_points, fixed_points, atol=1e-3) and moved == on_scan


def test_planner_probes_where_the_reading_tells_the_class_and_runs_on_real_probes():
    planner = script("planner_ceiling")
    labels = torch.arange(400).remainder(2)
    # candidate 0 reads the same for every class, candidate 1 touches class 1 only, candidate 2 at random
    library = torch.stack([torch.full((400,), 0.1), torch.where(labels == 1, 0.2, planner.MISS),
                           torch.rand(400, generator=torch.Generator().manual_seed(0)) * 0.5], 1)
    bins = torch.where(library == planner.MISS, 0, 1 + (library / 0.05).long()).numpy()
    cells = planner.cell_matrix(bins, labels.numpy(), 12, 2)
    entropy = planner.expected_entropy(cells, torch.ones(1, 400), 12, 2)[0]
    assert entropy.argmin() == 1 and entropy[1] == pytest.approx(0.0) and entropy[0] == pytest.approx(np.log(2))
    noisy = planner.expected_entropy(cells, torch.ones(1, 400), 12, 2,
                                     planner.SensorNoise(miss_prob=0.1, false_contact_prob=0.1))[0]
    assert 0 < noisy[1] < noisy[0] == pytest.approx(np.log(2))  # still the telling probe, no longer sure to tell
    queries = torch.tensor([[0.1, 0.2, 0.3], [0.1, planner.MISS, 0.3]])
    chosen, named = planner.probe_episodes(queries, library.T, cells, labels, 2, 12, 2, 0.005, 1e-3)
    assert chosen[:, 0].tolist() == [1, 1] and named[:, 0].tolist() == [1, 0]  # the telling probe first
    assert (chosen[:, 1] != 1).all()  # never twice
    fixed, named = planner.probe_episodes(queries, library.T, cells, labels, 2, 12, 2, 0.005, 1e-3,
                                          planner.fixed_sequence(np.array([0, 2])))
    assert fixed.tolist() == [[0, 2], [0, 2]] and named[:, 0].tolist() == [0, 0]  # ties: the first class
    advice = []  # what the planner would have probed at the states the fixed sequence reached
    followed, _ = planner.probe_episodes(queries, library.T, cells, labels, 2, 12, 2, 0.005, 1e-3,
                                         planner.fixed_sequence(np.array([0, 2])), advice=advice)
    assert followed.tolist() == fixed.tolist() and [a.argmin(1).tolist() for a in advice] == [[1, 1], [1, 1]]
    assert advice[0].isfinite().all() and (advice[1][:, 0] == np.inf).all()  # what was probed is not advised again
    # a faulty sensor: the first reading of the telling probe is a touch reported as a miss; the planner weighing
    # with the sensor's model probes it again, and the second reading outvotes the first
    faulty = torch.tensor([[[0.1, planner.MISS, 0.3]], [[0.1, 0.2, 0.3]]])
    noise = planner.SensorNoise(miss_prob=0.1, false_contact_prob=0.1)
    again, named = planner.probe_episodes(queries[:1], library.T, cells, labels, 2, 12, 2, 0.005, 1e-3,
                                          faulty=faulty, noise=noise)
    assert again.tolist() == [[1, 1]] and named.tolist() == [[0, 1]]
    _, named = planner.probe_episodes(queries[:1], library.T, cells, labels, 1, 12, 2, 0.005, 1e-3, faulty=faulty)
    assert named.tolist() == [[0]]  # the fault read as the sensor's word without its model
    ll = planner.log_likelihood(torch.tensor([[0.2]]), torch.tensor([[0.2, 0.21, planner.MISS]]), 0.01, 1e-3)
    assert ll[0].tolist() == pytest.approx([0.0, -0.5, np.log(1e-3)], rel=1e-4)
    # the first two probes chosen for the error two probes ahead: X names 60 % of the episodes outright (least
    # entropy one probe ahead, the greedy pick) but leaves the rest to one more halving; Y then Z name every one
    labels4 = torch.arange(400).remainder(4)
    x = torch.where((torch.arange(400) // 4).remainder(5) < 3, 0.1 * (labels4 + 1), planner.MISS)
    y, z = torch.where(labels4 < 2, 0.1, planner.MISS), torch.where(labels4.remainder(2) == 0, 0.1, planner.MISS)
    bins4 = planner.reading_bins(torch.stack([x, y, z], 1).numpy(), 0.05, 12)
    rules = planner.best_first_two(bins4, labels4.numpy(), 12, 4)
    assert rules["greedy"]["first"] == 0 and rules["greedy"]["accuracy"] == pytest.approx(0.8)
    assert rules["best"]["first"] in (1, 2) and rules["best"]["accuracy"] == pytest.approx(1.0)
    cells4 = planner.cell_matrix(bins4, labels4.numpy(), 12, 4)
    queries4 = torch.tensor([[planner.MISS, 0.1, 0.1], [0.4, planner.MISS, planner.MISS]])  # classes 0 and 3
    chosen, named = planner.probe_episodes(queries4, torch.stack([x, y, z]), cells4, labels4, 2, 12, 4, 0.005, 1e-3,
                                           planner.first_two(rules["best"], 0.05, 12))
    assert sorted(chosen[0].tolist()) == sorted(chosen[1].tolist()) == [1, 2] and named[:, 1].tolist() == [0, 3]
    # looking two probes ahead finds the same pair without trying every one: Y (or Z) first sets up the other
    two_step = planner.TwoStep(bins4, labels4.numpy(), 12, 4, probes=2)
    chosen, named = planner.probe_episodes(queries4, torch.stack([x, y, z]), cells4, labels4, 2, 12, 4, 0.005, 1e-3,
                                           two_step=two_step)
    assert sorted(chosen[0].tolist()) == sorted(chosen[1].tolist()) == [1, 2] and named[:, 1].tolist() == [0, 3]
    greedy, _ = planner.probe_episodes(queries4, torch.stack([x, y, z]), cells4, labels4, 2, 12, 4, 0.005, 1e-3)
    assert greedy[:, 0].tolist() == [0, 0]  # while one step ahead X looks best
    real = run("planner_ceiling", "--episodes", "16", "--library", "2048", "--n-probes", "3", "--places", "3",
               "--leans", "1.0", "--fixed", "--random", "--best-first-two", "--two-step", "2")
    assert real.returncode == 0, real.stderr[-2000:]
    result = json.loads(real.stdout.strip().splitlines()[-1])
    assert result["candidates"] == 9 and len(result["planner"]["accuracy"]) == 3
    assert result["fixed"]["tilt_deg"] == 0 and result["fixed"]["places"] == 3  # straight, one probe per place
    assert result["planner"]["repeats"] == result["fixed"]["repeats"] == result["random"]["repeats"] == 0  # without
    # faults never a candidate twice
    alone = run("planner_ceiling", "--episodes", "16", "--library", "2048", "--n-probes", "3", "--places", "3",
                "--leans", "1.0", "--random", "--no-planner", "--library-seed", "0", "--seed", "5")
    assert alone.returncode == 0, alone.stderr[-2000:]
    alone = json.loads(alone.stdout.strip().splitlines()[-1])
    assert "planner" not in alone and alone["library_seed"] == 0  # the library of --seed 0: the namer above
    assert alone["random"]["accuracy"] != result["random"]["accuracy"]  # other draws, the same namer
    assert all(0 <= a <= 1 for a in result["planner"]["accuracy"])
    assert len(result["two_step"]["accuracy"]) == 3
    assert len(result["best_first_two"]["accuracy"]) == 3 and result["first_two_on_library"]["best"]["accuracy"] >= \
        result["first_two_on_library"]["greedy"]["accuracy"]
    noisy = run("planner_ceiling", "--episodes", "16", "--library", "2048", "--n-probes", "3", "--places", "3",
                "--leans", "1.0", "--along-leans", "1.0", "--noise", "0.3")
    assert noisy.returncode == 0, noisy.stderr[-2000:]
    result = json.loads(noisy.stdout.strip().splitlines()[-1])
    assert result["candidates"] == 15 and result["along_leans"] == [1.0]  # 3 places x (straight, +-x, +-y)
    assert result["noise"] == 0.3 and all(0 <= a <= 1 for a in result["planner"]["accuracy"])
    bad = run("planner_ceiling", "--n-probes", "10", "--places", "1", "--leans")
    assert bad.returncode != 0 and "--n-probes 10: more than the 1 candidates" in bad.stderr
    bad = run("planner_ceiling", "--noise", "1.0")
    assert bad.returncode != 0 and "--noise 1.0: must be in [0, 1)" in bad.stderr
    bad = run("planner_ceiling", "--no-planner", "--fixed", "--save-rollouts", "x.npz")
    assert bad.returncode != 0 and "--no-planner: needs --fixed or --random, and no option" in bad.stderr
    bad = run("planner_ceiling", "--noise", "0.1", "--best-first-two")
    assert bad.returncode != 0 and "--best-first-two: needs" in bad.stderr


@pytest.mark.parametrize("along_leans", [[], [1.0]])  # leaning along the line too: a mirror image keeps those
def test_planner_library_shifts_and_mirror_images_read_as_moved_and_mirrored_objects_do(along_leans):
    labels = np.arange(4)  # every hg4 object
    poses = np.array([[0.05, 0.0, -0.25, 5.0, -4.0, 30.0], [-0.08, 0.02, -0.3, -6.0, 8.0, 100.0],
                      [0.1, -0.03, -0.22, 2.0, 3.0, 200.0], [-0.02, 0.04, -0.28, -3.0, -7.0, 300.0]])
    with ProbeSimulator("hg4", batch_size=8, mode="ideal") as sim:
        library, library_labels, positions = library_readings(sim, labels, poses, 5, 0.4, [1.0], 1, True, along_leans)
        step = 0.2 * 0.5 * (sim.scene.probe_y[1] - sim.scene.probe_y[0])  # 0.2 request units apart, in metres
        candidates = candidate_requests(5, 0.4, [1.0], along_leans)
        moved, mirrored = poses.copy(), poses * [-1, 1, 1, 1, -1, -1]  # x -> -x: Ry and Rz change sign
        moved[:, 1] += step
        as_moved = readings(sim, labels, moved, candidates)
        as_mirrored = readings(sim, labels, mirrored, candidates)
    # blocks of 4: shift -1, its mirror, shift 0, its mirror, shift +1, its mirror (all objects stay in range)
    assert library.shape == (24, len(candidates)) and library_labels.tolist() == labels.tolist() * 6
    assert (as_moved != MISS).any() and (as_mirrored != MISS).any()
    np.testing.assert_allclose(library[16:20], as_moved, atol=1e-4)
    np.testing.assert_allclose(library[12:16], as_mirrored, atol=1e-4)
    # where each library episode's object lies: across the line (mirrored: the other side) and along it (moved)
    np.testing.assert_allclose(positions[16:20], moved[:, :2], atol=1e-6)
    np.testing.assert_allclose(positions[12:16], mirrored[:, :2], atol=1e-6)
    np.testing.assert_allclose(positions[8:12], poses[:, :2], atol=1e-6)


def test_copy_teacher_copies_a_fixed_scan_from_the_probes_and_their_index(tmp_path):
    from hg.sim import PoseRegions, sample_episodes

    fit = subprocess.run([sys.executable, "-m", "hg.lightning.cli", "fit", "--config", str(ROOT / "configs" / "tiny.yaml"),
                          "--model.touch_set", "true", "--trainer.max_steps", "1"], capture_output=True, text=True,
                         env=ENV, cwd=tmp_path, timeout=300)
    assert fit.returncode == 0, fit.stderr[-2000:]
    checkpoint = next(tmp_path.glob("runs/haptic-glance/*/checkpoints/last.ckpt"))
    labels, poses = sample_episodes(PoseRegions(), "train", 64, 4, np.random.default_rng(0))
    scan = np.array([[0.0, 1.0, 0.0, 0.4], [0.0, -1.0, 0.0, 0.4], [0.3, 0.0, 0.0, 1.0], [-0.3, 1.0, 0.0, 0.0]])
    script("planner_ceiling").save_rollouts(tmp_path / "scan.npz", labels, poses, np.tile(scan, (64, 1, 1)), {})
    proc = run("copy_teacher", "--ckpt", str(checkpoint), "--teacher", str(tmp_path / "scan.npz"),
               "--episodes", "64", "--steps", "400")
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert set(result) >= {"pcrn", "pcrn_touch_set", "points"} and result["held_out"] == 8
    # the probes so far and their index say where a fixed scan goes next: the copy is close
    assert max(result["points"]["own"]) < 0.1 and result["points"]["lean_side"] == 1.0, result["points"]
    assert all(0 <= e <= 2 for state in ("pcrn", "pcrn_touch_set") for e in result[state]["own"])
    missing = run("copy_teacher", "--ckpt", str(tmp_path / "nope.ckpt"), "--teacher", str(tmp_path / "scan.npz"))
    assert missing.returncode != 0 and "nope.ckpt: checkpoint not found" in missing.stderr


def test_copy_planner_learns_a_teacher_s_candidate_sequence_and_probes_with_it(tmp_path):
    from hg.sim import PoseRegions, sample_episodes

    planner = script("planner_ceiling")
    meta = {"n_probes": 3, "places": 3, "span": 0.5, "leans": [1.0], "library": 256, "library_split": "train",
            "shifts": 0, "mirror": False, "sigma": 0.005, "mismatch": 1e-3, "bin": 0.01, "seed": 0}
    candidates = planner.candidate_requests(3, 0.5, [1.0])  # 3 places x (straight, +x, -x)
    labels, poses = sample_episodes(PoseRegions(), "train", 64, 4, np.random.default_rng(0))
    sequence = candidates[[4, 0, 8]]  # middle leaning +x, first place straight, last place leaning -x
    planner.save_rollouts(tmp_path / "scan.npz", labels, poses, np.tile(sequence, (64, 1, 1)), meta)
    proc = run("copy_planner", "--teacher", str(tmp_path / "scan.npz"), "--episodes", "32", "--steps", "300",
               "--hidden", "32")
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["top1"] == 1.0 and result["held_out"] == 8  # a fixed sequence is a function of the probe index
    assert result["copy"]["places"] == 3 and result["copy"]["tilt_deg"] == pytest.approx(2 / 3 * 26.57, abs=0.1)  # lean 1.0: 26.6 degrees
    assert result["fixed"]["tilt_deg"] == 0 and len(result["random"]["accuracy"]) == 3
    belief = run("copy_planner", "--teacher", str(tmp_path / "scan.npz"), "--episodes", "32", "--steps", "300",
                 "--hidden", "32", "--belief")  # reading the namer's belief too, it still copies the sequence
    assert belief.returncode == 0, belief.stderr[-2000:]
    found = json.loads(belief.stdout.strip().splitlines()[-1])
    assert found["belief"] and found["top1"] == 1.0 and found["copy"]["places"] == 3
    # taught on its own states too: the planner's picks there, not the scan's, join the teacher's 56 x 3 states
    dagger = run("copy_planner", "--teacher", str(tmp_path / "scan.npz"), "--episodes", "32", "--steps", "300",
                 "--hidden", "32", "--split", "val", "--dagger", "1", "--dagger-episodes", "16")
    assert dagger.returncode == 0, dagger.stderr[-2000:]
    rounds = json.loads(dagger.stdout.strip().splitlines()[-1])["dagger"]
    assert rounds[0]["samples"] == 56 * 3 + 16 * 3 and len(rounds[0]["copy_sampled"]) == 3
    assert 0 <= rounds[0]["advice_match"] < 1  # the planner is no fixed scan
    soft = run("copy_planner", "--teacher", str(tmp_path / "scan.npz"), "--episodes", "32", "--steps", "300",
               "--hidden", "32", "--soft", "0.05")
    assert soft.returncode == 0, soft.stderr[-2000:]
    found = json.loads(soft.stdout.strip().splitlines()[-1])["soft"][0]
    assert found["temperature"] == 0.05 and len(found["copy"]) == len(found["copy_sampled"]) == 3
    assert found["replayed_match"] < 1  # taught the planner's ranking, not the scan it was given
    off = np.tile(sequence, (64, 1, 1))
    off[:, 0, 0] = 0.1  # not one of the candidates
    planner.save_rollouts(tmp_path / "off.npz", labels, poses, off, meta)
    bad = run("copy_planner", "--teacher", str(tmp_path / "scan.npz"), "--belief", "--dagger", "1")
    assert bad.returncode != 0 and "--belief: not with --dagger or --soft" in bad.stderr
    bad = run("copy_planner", "--teacher", str(tmp_path / "off.npz"))
    assert bad.returncode != 0 and "--teacher: 64 requests are not candidates" in bad.stderr


def test_accuracy_by_cell_tells_unseen_positions_from_unseen_headings(tmp_path):
    from hg.sim import PoseRegions

    regions = PoseRegions()
    kinds = script("accuracy_by_cell").pose_kinds
    poses = regions.sample("test", 512, np.random.default_rng(0))
    whole = kinds(regions, poses, "test")
    x, y, rz = regions.cell_of(poses)
    assert whole.any() and (~whole).any()
    assert (regions.table[x[whole], y[whole]] == 2).all()  # every heading of those positions is held out
    assert ((regions.table[x[~whole], y[~whole]] == 0).any(-1)).all()  # the others' positions are trained on
    fit = subprocess.run([sys.executable, "-m", "hg.lightning.cli", "fit", "--config", str(ROOT / "configs" / "tiny.yaml"),
                          "--trainer.max_steps", "1"], capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=300)
    assert fit.returncode == 0, fit.stderr[-2000:]
    checkpoint = next(tmp_path.glob("runs/haptic-glance/*/checkpoints/last.ckpt"))
    proc = run("accuracy_by_cell", "--ckpt", str(checkpoint), "--episodes", "64", "--mode", "ideal")
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])[str(checkpoint)]
    assert result["unseen_position"]["episodes"] + result["unseen_heading"]["episodes"] == 64
    assert all(0 <= a <= 1 for r in result.values() for a in r["accuracy"] + r["accuracy_mean_action"])
    missing = run("accuracy_by_cell", "--ckpt", str(tmp_path / "nope.ckpt"))
    assert missing.returncode != 0 and "nope.ckpt: checkpoint not found" in missing.stderr


def test_accuracy_by_cell_names_a_choice_s_probes_as_the_planner_would(tmp_path):
    """--namer: a choice among the planner's candidates has its probes named by the planner's namer too, and the
    planner runs on the same episodes; the namer given the planner's own choices names as the planner did."""
    from hg.sim import PoseRegions, ProbeSimulator, sample_episodes

    planner = script("planner_ceiling")
    meta = {"n_probes": 4, "places": 3, "span": 0.5, "leans": [1.0], "library": 256, "library_split": "train",
            "shifts": 1, "mirror": True, "sigma": 0.005, "mismatch": 1e-3, "bin": 0.01, "seed": 0}
    labels, poses = sample_episodes(PoseRegions(), "train", 8, 4, np.random.default_rng(0))
    planner.save_rollouts(tmp_path / "teacher.npz", labels, poses,
                          np.tile(planner.candidate_requests(3, 0.5, [1.0])[:4], (8, 1, 1)), meta)
    with ProbeSimulator("hg4", batch_size=64, mode="ideal", seed=0) as sim:
        namer = script("copy_planner").BayesNamer(meta, sim, PoseRegions(), 4)
        test_labels, test_poses = sample_episodes(PoseRegions(), "test", 64, 4, np.random.default_rng(1))
        query = planner.readings(sim, test_labels, test_poses, planner.candidate_requests(3, 0.5, [1.0]))
    chosen, named = namer.probe(query, 4, None)
    assert np.array_equal(namer.probe(query, 4, chosen)[1], named)
    # the namer's belief (copy_planner.py --belief): before any probe the library's own, as likely on either side
    # of the line (it is mirrored); a copy reading it as its probes come in reads what a replay of them gives
    beliefs = namer.beliefs(torch.from_numpy(chosen), torch.from_numpy(query))
    assert beliefs.shape == (4 * 64, 4 + 4)
    torch.testing.assert_close(beliefs[:, :4].sum(1), torch.ones(4 * 64))
    torch.testing.assert_close(beliefs[:64], beliefs[:1].expand(64, -1))
    assert beliefs[0, 7] == pytest.approx(0.5, abs=1e-4) and not torch.allclose(beliefs[192:], beliefs[:64])

    class Reader(torch.nn.Module):  # chooses the first unprobed candidate, keeping what it read
        read = []

        def forward(self, x):
            self.read.append(x[:, -8:])
            return torch.zeros(len(x), query.shape[1])

    module = script("copy_planner")
    first, _ = namer.probe(query, 4, module.network_choice(Reader(), 4, 0.6, None, namer))
    torch.testing.assert_close(torch.cat(Reader.read), namer.beliefs(torch.from_numpy(first), torch.from_numpy(query)))
    assert not np.array_equal(namer.probe(query, 4, chosen[:, ::-1].copy())[0], chosen)
    fit = subprocess.run([sys.executable, "-m", "hg.lightning.cli", "fit", "--config", str(ROOT / "configs" / "tiny.yaml"),
                          "--trainer.max_steps", "1", "--model.location", "candidates", "--model.candidate_places",
                          "3", "--model.candidate_leans", "[1.0]", "--model.choice_reads_probes", "true"],
                         capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=300)
    assert fit.returncode == 0, fit.stderr[-2000:]
    checkpoint = next(tmp_path.glob("runs/haptic-glance/*/checkpoints/last.ckpt"))
    proc = run("accuracy_by_cell", "--ckpt", str(checkpoint), "--episodes", "32", "--mode", "ideal", "--namer",
               str(tmp_path / "teacher.npz"), "--planner")
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    for kind, accuracy in result["planner"].items():
        model = result[str(checkpoint)][kind]
        assert len(accuracy) == 4 and len(model["accuracy_namer"]) == len(model["accuracy_on_planner_probes"]) == 4
        assert all(0 <= a <= 1 for a in accuracy + model["accuracy_namer"] + model["accuracy_on_planner_probes"])
    meta["places"] = 5
    planner.save_rollouts(tmp_path / "other.npz", labels, poses,
                          np.tile(planner.candidate_requests(5, 0.5, [1.0])[:4], (8, 1, 1)), meta)
    other = run("accuracy_by_cell", "--ckpt", str(checkpoint), "--episodes", "32", "--mode", "ideal", "--namer",
                str(tmp_path / "other.npz"))
    assert other.returncode != 0 and "its 9 candidates are not the --namer teacher's 15" in other.stderr


def test_noise_merge_adds_the_namer_alone_beside_ours(tmp_path):
    """Ours' runs that logged their library namer alone on the same rollouts give a row of their own."""
    (tmp_path / "noise_runs").mkdir()
    (tmp_path / "table1.json").write_text(json.dumps({"best_pcrn": "namer_row"}))
    for rate, seed, ours, alone in ((0.0, 0, 0.95, 0.96), (0.1, 0, 0.75, 0.84), (0.1, 1, 0.77, 0.86)):
        record = {"model": "ours", "row": "namer_row", "rate": rate, "seed": seed, "accuracy": ours,
                  "accuracy_namer_alone_per_probe": [0.3] * 9 + [alone], "label": "ours: namer_row after 10 probes",
                  "commit": "abc1234", "hardware": "test"}
        (tmp_path / "noise_runs" / f"ours-namer_row-rate{round(rate * 100):02d}-seed{seed}.json").write_text(
            json.dumps(record))
    trained = {"model": "ours_trained", "row": "namer_row", "rate": 0.1, "seed": 0, "accuracy": 0.8,
               "accuracy_namer_alone_per_probe": [0.3] * 9 + [0.9], "label": "ours trained at the rate: namer_row",
               "commit": "abc1234", "hardware": "test"}
    (tmp_path / "noise_runs" / "ours_trained-namer_row-rate10-seed0.json").write_text(json.dumps(trained))
    merged = run("reproduce_noise", "--merge-only", "--out", str(tmp_path))
    assert merged.returncode == 0, merged.stderr[-2000:]
    summary = json.loads(merged.stdout.strip().splitlines()[-1])
    assert summary["ours"] == [0.95, 0.76] and summary["ours_namer_alone"] == [0.96, 0.85]  # ours' namer alone only
    assert summary["ours_trained-namer_row"] == [0.8] and summary["ours_trained-namer_row-namer_alone"] == [0.9]
    text = (tmp_path / "noise.md").read_text()
    assert "ours, its namer alone: namer_row" in text and "ours trained at the rate, its namer alone: namer_row" in text


def test_ours_trained_copying_a_planner_copies_one_planned_at_the_rate(tmp_path):
    noise = script("reproduce_noise")
    (tmp_path / "t_noise10.npz").write_bytes(b"")
    assert noise.noise_teachers(None, [str(tmp_path / "t.npz")], 0.1) == [str(tmp_path / "t_noise10.npz")]
    assert noise.noise_teachers([str(tmp_path / "t_noise{pct}.npz")], [], 0.1) == [str(tmp_path / "t_noise10.npz")]
    with pytest.raises(FileNotFoundError, match=r"t_noise30.npz: no teacher planned at rate 0.3; write one with "
                                                r"scripts/plan.py, the arguments of the noise-free "
                                                r"teacher.*--noise 0.3 --save-rollouts"):
        noise.noise_teachers(None, [str(tmp_path / "t.npz")], 0.3)


def test_planner_under_noise_plans_with_faults_and_reuses_the_table_run_at_rate_0(tmp_path):
    noise = script("reproduce_noise")
    with pytest.raises(FileNotFoundError, match="planner-seed0.json: no table run of the planner"):
        noise.plan_under_noise(0, 0.0, 16, tmp_path)
    fake_run(tmp_path, "planner", 0, [0.4] * 9 + [0.98])
    record = json.loads((tmp_path / "runs" / "planner-seed0.json").read_text())
    (tmp_path / "runs" / "planner-seed0.json").write_text(json.dumps(record | {"command": "scripts/planner_ceiling.py"}))
    reused = noise.plan_under_noise(0, 0.0, 16, tmp_path)
    assert reused["accuracy"] == 0.98 and reused["commit"] == "abc1234"  # the table run's, not this commit
    tiny = ("--library-split", "train", "--library", "128")
    faulty = noise.plan_under_noise(0, 0.5, 16, tmp_path, library=tiny)
    assert faulty["command"].endswith("--seed 0 --noise 0.5") and len(faulty["accuracy_per_probe"]) == 10
    assert faulty["accuracy"] == faulty["accuracy_per_probe"][-1] and 0 <= faulty["accuracy"] <= 1


def test_noise_ceiling_reads_the_same_probes_with_faults_dropped_and_without_faults(tmp_path):
    """At rate 1 every reading is corrupted: the script counts them all, and the namer told which readings are
    faulty has nothing left to read, so its accuracy never moves from the first probe's."""
    teacher = tmp_path / "teacher.npz"
    made = subprocess.run([sys.executable, str(ROOT / "scripts" / "planner_ceiling.py"), "--library-split", "train",
                           "--split", "train", "--library", "256", "--episodes", "8", "--n-probes", "4",
                           "--save-rollouts", str(teacher)], capture_output=True, text=True, env=ENV, timeout=300)
    assert made.returncode == 0, made.stderr[-2000:]
    fit = subprocess.run([sys.executable, "-m", "hg.lightning.cli", "fit", "--config", str(ROOT / "configs" / "tiny.yaml"),
                          "--trainer.max_steps", "1", "--model.location", "candidates", "--model.choice_reads_probes",
                          "true"], capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=300)
    assert fit.returncode == 0, fit.stderr[-2000:]
    checkpoint = next(tmp_path.glob("runs/haptic-glance/*/checkpoints/last.ckpt"))
    proc = run("noise_ceiling", "--ckpt", str(checkpoint), "--namer", str(teacher), "--rates", "1.0", "0.2",
               "--episodes", "32")
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["1.0"]["faults_per_episode"] == 4  # tiny: 4 probes, all faulty
    assert 0 < result["0.2"]["faults_per_episode"] < 4
    for rate in ("1.0", "0.2"):
        for shown in ("policy_reads_faulty", "policy_reads_clean"):
            assert set(result[rate][shown]) == {"faulty", "faults_dropped", "clean"}
            assert all(len(a) == 4 and all(0 <= v <= 1 for v in a) for a in result[rate][shown].values())
    assert len(set(result["1.0"]["policy_reads_faulty"]["faults_dropped"])) == 1
    assert result["commit"] and result["split"] == "val" and result["episodes"] == 32
    missing = run("noise_ceiling", "--ckpt", str(tmp_path / "nope.ckpt"), "--namer", str(teacher))
    assert missing.returncode != 0 and "nope.ckpt: checkpoint not found" in missing.stderr
    bad = run("noise_ceiling", "--ckpt", str(checkpoint), "--namer", str(teacher), "--rates", "0")
    assert bad.returncode != 0 and "--rates 0.0: a fault rate must be in (0, 1]" in bad.stderr
