"""The Table 1 and noise scripts: rows as compositions that predict and probe as they say, real tiny runs (resumed
after SIGTERM, never recomputed, refused when asked as another run), a row scoring another row's checkpoints, the
merge's counts and checks, and the ablations page made from the hg4 records."""
import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
TINY = "configs/parts/tiny.yaml"
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


def config(tmp_path: Path, name: str, content: dict) -> str:
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(content))
    return str(path)


def fake_record(table1, out: Path, row: str, seed: int, accuracy: list[float], val: float | None = 0.5,
                fingerprint: str = "abc", **facts) -> Path:
    spec = table1.ROWS[row]
    record = {"row": row, "label": spec.label, "prediction": spec.prediction, "probes": spec.probes,
              "definition": spec.definition(), "split": "test", "seed": seed, "composition": list(spec.configs),
              "overrides": [], "command": f"hg fit --config {row}", "accuracy": accuracy,
              "accuracy_mean_action": accuracy if spec.probes == "learned" else None, "best_val_acc": val,
              "train_wall_s": 1.0, "parallel_jobs": 1, "test_episodes": 2048, "test_fingerprint": fingerprint,
              "commit": "abc1234", "hardware": "cpu", **facts}
    path = table1.record_path(out, row, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record))
    return path


def test_rows_are_compositions_that_predict_and_probe_as_they_say():
    from hg.lightning.cli import cli
    from hg.planner import teacher_meta

    table1 = script("reproduce_table1")
    assert {"pcrn_fc_as_written", "lstm", "random", "line_scan", "side_scan", "gaussian_on_side_scan", "planner_copy",
            "planner_copy_library", "planner_copy_mixed", "planner65k"} <= set(table1.ROWS)
    old_rows = {json.loads(p.read_text())["row"] for p in (ROOT / "docs/results/runs").glob("*.json")}
    for name, row in table1.ROWS.items():
        assert row.was is None or row.was in old_rows, f"{name} replaces {row.was}, no hg4 row of that name"
        if row.cloud:  # a point-cloud baseline: its own net on surface points, no composition, no probing
            assert row.prediction == "learned" and row.probes == "random" and not row.configs and not row.plan
            continue
        if row.plan:  # the planner's own Bayes classifier names its probes
            assert row.prediction == "library" and not row.configs and row.probes in ("planner", "fixed", "random")
            continue
        model = cli([a for c in (*row.configs, TINY) for a in ("--config", str(ROOT / c))] + ["--trainer.logger",
                                                                                             "false"], run=False).model
        policy = type(model.policy).__name__
        probes = "learned" if model.policy.learned else "random" if policy == "RandomProbes" else "fixed"
        assert probes == row.probes, f"{name}: its policy {policy} probes '{probes}', the row says '{row.probes}'"
        assert (model.library_source is not None) == (row.prediction != "learned"), name
        if row.scores:  # the scored row's composition, with evaluation-only parts after it
            assert row.configs[:len(table1.ROWS[row.scores].configs)] == table1.ROWS[row.scores].configs
    # the rows of probes placed by no one are named by planner_copy's library classifier: its library's recipe
    teacher = yaml.safe_load((ROOT / table1.LIBRARY).read_text())["model"]["library_classifier"]["teacher"]
    meta = teacher_meta([str(ROOT / teacher)])
    for name in ("candidate_scan_library", "random_candidates_library"):
        plan = table1.ROWS[name].plan
        asked = {flag: plan[plan.index(flag) + 1] for flag in ("--library", "--shifts", "--library-seed",
                                                               "--library-split")}
        assert asked == {"--library": str(meta["library"]), "--shifts": str(meta["shifts"]),
                         "--library-seed": str(meta["seed"]), "--library-split": meta["library_split"]}
        assert ("--mirror" in plan) == meta["mirror"] and f"--{table1.ROWS[name].probes}" in plan


def test_on_another_object_set_the_rows_take_its_own_teachers_and_no_mirror_for_chiral_objects(tmp_path, monkeypatch):
    """pyb10 has chiral objects: its planner rows plan without the library's mirror images, and the planner copy's
    rows read pyb10's teacher files; a set without teacher files is refused with the command that writes them."""
    table1 = script("reproduce_table1")
    pyb10 = "data/objects/pyb10"
    plan, overrides = table1.on_set(table1.ROWS["planner65k"], pyb10, [])
    assert "--mirror" in table1.ROWS["planner65k"].plan and "--mirror" not in plan
    assert table1.on_set(table1.ROWS["planner65k"], "hg4", [])[0] == table1.ROWS["planner65k"].plan
    teachers = [f"data/planner/across_line/pyb10_train65k_s{s}.npz" for s in (10, 20)]
    row = table1.ROWS["planner_copy_library"]
    plan, overrides = table1.on_set(row, pyb10, list(row.configs))
    assert plan == () and overrides[:2] == ("--data.objects", pyb10)
    assert json.loads(overrides[overrides.index("--model.warmup.init_args.teachers") + 1]) == teachers
    assert overrides[overrides.index("--model.library_classifier.teacher") + 1] == teachers[0]
    # a copy of pyb10 under another name has no teacher files
    shutil.copytree(ROOT / pyb10, tmp_path / "my_objects")
    with pytest.raises(FileNotFoundError, match=r"my_objects_train65k_s10.npz: no teacher file .*--shifts 5 --split"):
        table1.on_set(table1.ROWS["planner_copy"], str(tmp_path / "my_objects"), list(table1.PLANNER_COPY))
    # a part added to a row's composition (--add-config) counts too
    with pytest.raises(FileNotFoundError, match=r"my_objects_train65k_s10.npz"):
        table1.on_set(table1.ROWS["line_scan"], str(tmp_path / "my_objects"),
                      ["configs/line_scan.yaml", table1.LIBRARY])
    assert table1.on_set(table1.ROWS["line_scan"], str(tmp_path / "my_objects"), ["configs/line_scan.yaml"])[1] == (
        "--data.objects", str(tmp_path / "my_objects"))


def test_point_cloud_rows_train_on_surface_points_and_are_merged_beside_the_probing_rows(tmp_path, monkeypatch):
    """PointNet and DGCNN (3 steps here): a record on the table's test episodes with the accuracy reading the first
    k of the 10 points, k = 1..10 (DGCNN reads fewer points than its 9 neighbours as one neighbourhood), merged."""
    table1 = script("reproduce_table1")
    monkeypatch.setattr(table1, "CLOUD_STEPS", 3)
    for row in ("pointnet", "dgcnn"):
        table1.train_and_test(row, 0, tmp_path / "runs", tmp_path, 1, test_episodes=64)
        record = json.loads(table1.record_path(tmp_path, row, 0).read_text())
        assert record["max_steps"] == 3 and record["definition"]["cloud"] == row and record["split"] == "test"
        assert len(record["accuracy"]) == 10 and all(0 <= a <= 1 for a in record["accuracy"])
        table1.check_definition(table1.record_path(tmp_path, row, 0), record, [])  # a second invocation reuses it
    fake_record(table1, tmp_path, "line_scan", 0, [0.3] * 10, fingerprint=record["test_fingerprint"],
                test_episodes=64)
    merged = table1.merge(tmp_path)  # the same test episodes as a probing row's: merged beside it
    assert set(merged) == {"commit", "line_scan", "pointnet", "dgcnn"}
    assert "PointNet on 10 clean surface points" in (tmp_path / "table1.md").read_text()


def test_changed_hyperparameters_compares_injected_parts_field_by_field():
    from hg.lightning.experiment import changed_hyperparameters

    before = {"policy": {"class_path": "hg.policies.GaussianPolicy", "init_args": {"std_floor": 0.05, "anchor": 0.0}},
              "heads": [{"class_path": "hg.nets.FCClassifier", "init_args": {"hidden": 256}}],
              "loss": {"gamma": 0.95}, "warmup": None, "library_classifier": None, "_instantiator": "a"}
    saved = {"hyper_parameters": before, "datamodule_hyper_parameters": {"noise": {"miss_prob": 0.0},
                                                                          "test_episodes": 2048}}
    same = json.loads(json.dumps(before)) | {"_instantiator": "b", "library_classifier": {"teacher": "x.npz"}}
    same["policy"]["init_args"]["truncated"] = False  # an argument added to the code since: its default is the old way
    assert changed_hyperparameters(saved, same, {"noise": {"miss_prob": 0.0}, "test_episodes": 32}) == []
    other = json.loads(json.dumps(before))
    other["policy"]["init_args"]["anchor"] = 1.0
    other["heads"][0]["init_args"]["hidden"] = 32
    other["loss"]["gamma"] = 0.5
    other["warmup"] = {"class_path": "hg.rl.FollowPrior", "init_args": {"steps": 10}}
    assert changed_hyperparameters(saved, other, {"noise": {"miss_prob": 0.1}}) == [
        "model.heads.0.init_args.hidden=256 (now 32)", "model.loss.gamma=0.95 (now 0.5)",
        "model.policy.init_args.anchor=0.0 (now 1.0)",
        'model.warmup=null (now {"class_path": "hg.rl.FollowPrior", "init_args": {"steps": 10}})',
        "data.noise.miss_prob=0.0 (now 0.1)"]
    other = json.loads(json.dumps(before))
    other["policy"] = {"class_path": "hg.policies.LineScan", "init_args": {}}  # another class: one difference
    assert changed_hyperparameters(saved, other) == [
        "model.policy.class_path=hg.policies.GaussianPolicy (now hg.policies.LineScan)"]


def test_a_file_setting_moved_to_another_clone_is_the_same_setting_only_with_the_same_bytes(tmp_path):
    from hg.lightning.experiment import changed_hyperparameters

    here, there, edited = tmp_path / "a.urdf", tmp_path / "b.urdf", tmp_path / "c.urdf"
    here.write_text("<robot/>"), there.write_text("<robot/>"), edited.write_text("<robot name='x'/>")
    saved = {"datamodule_hyper_parameters": {"robot": str(here)}}
    assert changed_hyperparameters(saved, {}, {"robot": str(there)}) == []
    assert changed_hyperparameters(saved, {}, {"robot": str(edited)}) == [f'data.robot="{here}" (now "{edited}")']
    assert changed_hyperparameters(saved, {}, {"robot": str(tmp_path / "gone.urdf")}) != []
    assert changed_hyperparameters({"datamodule_hyper_parameters": {"name": "a" * 300}}, {}, {"name": "b" * 300})


def test_a_run_stopped_by_sigterm_resumes_is_recorded_once_and_refuses_another_composition(tmp_path):
    out, ckpt = tmp_path / "results", tmp_path / "ckpt"
    args = ["--rows", "random", "--seeds", "0", "--test-episodes", "32", "--out", str(out), "--runs-dir", str(ckpt),
            "--threads", "1", "--add-config", TINY]
    bad = run("reproduce_table1", *args[:-3], "0")  # --threads 0, refused before anything runs
    assert bad.returncode != 0 and "--threads 0: must be >= 1" in bad.stderr and not out.exists()
    endless = config(tmp_path, "endless", {"trainer": {"max_steps": 100000}})
    parent = subprocess.Popen([sys.executable, str(ROOT / "scripts" / "reproduce_table1.py"), *args, "--add-config",
                               endless], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)
    last = ckpt / "random-seed0" / "checkpoints" / "last.ckpt"
    deadline = time.time() + 120
    while not last.is_file() and time.time() < deadline and parent.poll() is None:
        time.sleep(0.2)
    assert last.is_file(), "the child never wrote a checkpoint"
    parent.send_signal(signal.SIGTERM)  # the parent stops its child: Lightning ends the fit at the next step
    stdout, stderr = parent.communicate(timeout=120)
    assert parent.returncode != 0 and "stopped by SIGTERM" in stderr, stderr[-2000:]
    assert "random-seed0: stopped before writing random-seed0.json" in stdout
    assert not (out / "table1_runs").exists()
    first = run("reproduce_table1", *args)  # resumes from the stopped run's checkpoint, to the tiny max_steps
    assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-2000:]
    assert "random-seed0: done in" in first.stdout
    record = json.loads((out / "table1_runs" / "random-seed0.json").read_text())
    assert record["resumed_from_step"] >= 2 and record["split"] == "test" and record["test_episodes"] == 32
    assert record["composition"] == ["configs/random.yaml", TINY] and record["prediction"] == "learned"
    assert record["command"].startswith(f"hg fit --config configs/random.yaml --config {TINY} --seed_everything 0 ")
    assert record["probes"] == "random" and record["accuracy_mean_action"] is None  # a fixed policy has no mean
    assert len(record["accuracy"]) == 4 and record["torch_threads"] == 1  # tiny: 4 probes; 1 thread as asked
    again = run("reproduce_table1", *args)
    assert again.returncode == 0 and "0 runs to train" in again.stdout
    assert json.loads(again.stdout.strip().splitlines()[-1])["random"] == record["accuracy"]
    assert not (out / "table1.md").exists()  # training never rewrites the table
    other = run("reproduce_table1", *args, "--add-config", endless)  # asked as another composition: not this run
    assert other.returncode != 0 and "random-seed0.json: made with" in other.stderr
    # the checkpoint folder, asked to resume as another run (another learning rate): refused, untouched
    from hg.lightning.experiment import fit_and_test

    before = last.read_bytes()
    (last.parent / "last-v1.ckpt").write_bytes(before)  # as a resume in a moved folder left it before c34c920
    with pytest.raises(ValueError, match=r"last-v1.ckpt beside last.ckpt; the newest state may not be last.ckpt"):
        fit_and_test([ROOT / "configs/random.yaml", ROOT / TINY], 0, ckpt / "random-seed0", eval_seed=0,
                     test_episodes=32)
    (last.parent / "last-v1.ckpt").unlink()
    lr = config(tmp_path, "lr", {"model": {"lr": 0.01}})
    with pytest.raises(ValueError, match=r"last.ckpt: trained with model.lr=0.001 \(now 0.01\).*Move .* away"):
        fit_and_test([ROOT / "configs/random.yaml", ROOT / TINY, lr], 0, ckpt / "random-seed0", eval_seed=0,
                     test_episodes=32)
    assert last.read_bytes() == before


def test_two_rows_run_as_ray_tasks_and_a_second_invocation_trains_nothing(tmp_path, monkeypatch):
    out, ckpt = tmp_path / "results", tmp_path / "ckpt"
    args = ["--rows", "random", "line_scan", "--seeds", "0", "--test-episodes", "32", "--out", str(out), "--runs-dir",
            str(ckpt), "--threads", "1", "--jobs", "2", "--add-config", TINY]
    first = run("reproduce_table1", *args)
    assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-2000:]
    assert "2 jobs on a local Ray instance (num_cpus=2), each a task of num_cpus=1" in first.stdout
    for row in ("random", "line_scan"):
        assert f"{row}-seed0: done in" in first.stdout
        record = json.loads((out / "table1_runs" / f"{row}-seed0.json").read_text())
        assert record["parallel_jobs"] == 2 and record["torch_threads"] == 1 and record["test_episodes"] == 32
        log = (ckpt / f"{row}-seed0" / "log.txt").read_text()  # the child's log, headed by the Ray task that ran it
        assert log.startswith(f"== {row}-seed0 on ") and "(Ray task " in log and f"--one {row} 0 " in log
    again = run("reproduce_table1", *args)  # resumed from the records: nothing trained, no Ray started
    assert again.returncode == 0 and "0 runs to train: none" in again.stdout and "jobs on" not in again.stdout
    # a row that scores another row's checkpoints waits for that row's run of the same seed, and only for it
    table1 = script("reproduce_table1")
    asked = []
    monkeypatch.setattr(table1, "run_jobs", lambda jobs, *rest: asked.extend(jobs) or 0)
    monkeypatch.setattr(sys, "argv", ["reproduce_table1.py", "--out", str(tmp_path / "other"), "--rows",
                                      "planner_copy_mixed", "planner_copy", "--seeds", "0", "1"])
    table1.main()
    assert [(j.name, j.after) for j in asked] == [
        ("planner_copy-seed0", ()), ("planner_copy-seed1", ()), ("planner_copy_mixed-seed0", ("planner_copy-seed0",)),
        ("planner_copy_mixed-seed1", ("planner_copy-seed1",))]


def test_rows_scoring_planner_copy_read_its_checkpoints_and_feed_the_noise_study(tmp_path, monkeypatch):
    """planner_copy trained, then scored by its library and mixed rows (its best checkpoint, nothing trained); the
    merge counts each row's test reads; the noise study tests the mixed row's checkpoints under faults."""
    table1 = script("reproduce_table1")
    out, ckpt = tmp_path / "results", tmp_path / "ckpt"
    ten = config(tmp_path, "ten", {"data": {"n_probes": 10}})  # the teachers' episodes have 10 probes
    small = config(tmp_path, "small", {"data": {"n_probes": 10}, "model": {"library_classifier": {"episodes": 64}}})
    with pytest.raises(FileNotFoundError, match="row planner_copy_mixed scores the checkpoints of row planner_copy; "
                                                "run its seed 0 first"):
        table1.train_and_test("planner_copy_mixed", 0, ckpt, out, 1, 32, (TINY, small))
    table1.train_and_test("planner_copy", 0, ckpt, out, 1, 32, (TINY, ten))
    for row in ("planner_copy_mixed", "planner_copy_library"):
        table1.train_and_test(row, 0, ckpt, out, 1, 32, (TINY, small))
    copy, mixed, library = (json.loads(table1.record_path(out, r, 0).read_text())
                            for r in ("planner_copy", "planner_copy_mixed", "planner_copy_library"))
    assert mixed["best_checkpoint"] == library["best_checkpoint"] == copy["best_checkpoint"]
    assert mixed["train_wall_s"] == 0 and mixed["scores_checkpoint_of"] == "planner_copy"
    assert mixed["command"].startswith(f"hg test --ckpt_path {copy['best_checkpoint']} --config configs/planner_copy")
    assert mixed["composition"][:5] == [*table1.PLANNER_COPY, table1.LIBRARY]
    columns = mixed["test_columns"]  # every prediction of the same rollouts, each row reporting its own
    assert mixed["accuracy"] == columns["stochastic_mixed"] and library["accuracy"] == columns["stochastic_library"]
    assert copy["accuracy"] == columns["stochastic"] == library["test_columns"]["stochastic"]
    assert "stochastic_library" not in copy["test_columns"] and len(mixed["accuracy"]) == 10
    summary = table1.merge(out)
    saved = json.loads((out / "table1.json").read_text())["rows"]
    assert summary["planner_copy_mixed"] == mixed["accuracy"]
    assert [saved[r]["test_reads"] for r in ("planner_copy", "planner_copy_library", "planner_copy_mixed")] == [1, 1, 1]
    assert saved["planner_copy_library"]["prediction"] == "library" and saved["planner_copy"]["probes"] == "learned"
    text = (out / "table1.md").read_text()
    assert "| planner_copy's probes, named by the library classifier alone | library | learned | 1 |" in text
    assert (out / "table1.png").read_bytes()[:4] == b"\x89PNG"
    # our model under sensor noise: the mixed row's checkpoint and composition, its test episodes, readings corrupted
    noise = script("reproduce_noise")
    monkeypatch.setattr(sys, "argv", ["reproduce_noise.py", "--models", "ours", "--rates", "0", "0.5", "--seeds",
                                      "0", "--out", str(out), "--runs-dir", str(tmp_path / "noise")])
    noise.main()
    clean, noisy = (json.loads((out / "noise_runs" / f"ours-planner_copy_mixed-rate{r}-seed0.json").read_text())
                    for r in ("00", "50"))
    assert clean["accuracy_per_probe"] == mixed["accuracy"]  # rate 0 is the table's own test
    assert clean["accuracy_library_per_probe"] == library["accuracy"]
    assert noisy["checkpoint"] == copy["best_checkpoint"] and len(noisy["accuracy_library_per_probe"]) == 10
    assert noisy["accuracy_per_probe"] != clean["accuracy_per_probe"]  # half the readings corrupted
    merged = json.loads((out / "noise.json").read_text())["models"]
    assert merged["ours"]["rates"] == [0.0, 0.5] and merged["ours_library"]["accuracy"][0] == library["accuracy"][-1]
    # trained at a rate, a row copying the planner copies teachers planned at that rate: none written for 10 %
    with pytest.raises(FileNotFoundError, match=r"train65k_s10_noise10.npz: no teacher planned at rate 0.1; write "
                                                r"one with scripts/plan.py"):
        noise.noise_training_args(copy["composition"], 0.1, None)


def test_a_planner_row_plans_on_the_test_episodes_and_is_merged_beside_the_learned_rows(tmp_path):
    table1 = script("reproduce_table1")
    out = tmp_path / "results"
    table1.ROWS["tiny_scan"] = table1.Row("tiny straight scan", "library", "fixed",
                                          plan=("--library-split", "train", "--library", "128", "--fixed",
                                                "--no-planner"))
    try:
        table1.train_and_test("tiny_scan", 0, tmp_path / "ckpt", out, 1, test_episodes=16)
        record = json.loads(table1.record_path(out, "tiny_scan", 0).read_text())
        assert record["command"] == ("scripts/plan.py --library-split train --library 128 --fixed --no-planner "
                                     "--objects hg4 --split test --episodes 16 --table-episodes --mode arm --seed 0")
        assert record["plan_args"] == record["command"].split()[1:] and record["best_checkpoint"] is None
        assert len(record["accuracy"]) == 10 and all(0 <= a <= 1 for a in record["accuracy"])
        fake_record(table1, out, "side_scan", 0, [0.3] * 10, fingerprint=record["test_fingerprint"], test_episodes=16)
        table1.merge(out)
        # the second object set: its own records and table beside hg4's, with what the table must say of itself
        pyb10 = str(ROOT / "data" / "objects" / "pyb10")
        table1.train_and_test("tiny_scan", 0, tmp_path / "ckpt", out, 1, test_episodes=16, objects=pyb10)
        table1.merge(out, objects=pyb10)
    finally:
        del table1.ROWS["tiny_scan"]
    hg4, second = (json.loads((out / f"table1{s}.json").read_text()) for s in ("", "_pyb10"))
    assert hg4["objects"] == "hg4" and second["objects"] == pyb10 and second["commit"] == hg4["commit"]
    assert set(second["rows"]) == {"tiny_scan"} and second["test_fingerprint"] != hg4["test_fingerprint"]
    assert second["rows"]["tiny_scan"]["test_reads"] == 1 and len(second["rows"]["tiny_scan"]["accuracy"]) == 10
    assert {e["prediction"] for e in second["rows"].values()} == {"library"}
    for table in (hg4, second):  # the new regions: every test pose 2 cm or more from a training pose
        assert 0.02 <= table["heldout_min_distance_m"] <= 0.1
    text = (out / "table1.md").read_text()
    assert "| tiny straight scan | library | fixed | 1 |" in text
    assert f"| tiny straight scan | `{record['command']}` |" in text
    assert "No PCRN row with a learned policy yet: no target read." in text


def test_a_second_object_set_is_read_against_its_own_targets():
    """#56 on the second set: the learned policy picked on validation (among rows with all seeds), 0.05 above the best
    fixed scan and within 0.03 of the planner after the last probe; never a point-cloud baseline's figures."""
    table1 = script("reproduce_table1")

    def entry(row: str, acc: float, val: float | None = None, seeds: tuple[int, ...] = (0, 1, 2)) -> dict:
        return {"label": table1.ROWS[row].label, "accuracy": [acc] * 10, "seeds": list(seeds),
                **({} if val is None else {"best_val_acc": val})}

    table = {"choice_on_side_scan": entry("choice_on_side_scan", 0.50, val=0.6),
             "pcrn_fc": entry("pcrn_fc", 0.70, val=0.9, seeds=(0,)),  # better, but one seed
             "side_scan": entry("side_scan", 0.44), "line_scan": entry("line_scan", 0.2),
             "planner65k": entry("planner65k", 0.52), "pointnet": entry("pointnet", 0.9)}
    text = "\n".join(table1.second_set_targets(table))
    assert "a choice among candidates started on the side-picking scan" in text.splitlines()[0]
    assert "Above every fixed scan by >= 0.05 after 10 probes: met (+0.060 against side-picking scan" in text
    assert "Within 0.03 of the planner after 10 probes: met (-0.020 against greedy information-gain planner" in text
    table["planner65k"] = entry("planner65k", 0.54)
    assert "Within 0.03 of the planner after 10 probes: not met (-0.040" in "\n".join(
        table1.second_set_targets(table))


def test_merge_chooses_on_validation_compares_like_with_like_and_refuses_mixed_or_stale_records(tmp_path):
    table1 = script("reproduce_table1")
    # the same heads behind the policy's probes and behind its scan's (test_columns.prior), seed by seed
    fake_record(table1, tmp_path, "gaussian_on_side_scan", 0, [0.9] * 10, val=0.6,  # best on test, worse on val
                test_columns={"prior": [0.85] * 10})
    fake_record(table1, tmp_path, "gaussian_on_side_scan", 1, [0.95] * 10, val=0.6, test_columns={"prior": [0.9] * 10})
    for seed, prior in ((0, 0.2), (1, 0.5)):  # above its scan on the mean, in one seed only; its mean action in both
        fake_record(table1, tmp_path, "choice_on_side_scan", seed, [0.4] * 10, val=0.1,
                    test_columns={"prior": [prior] * 10}, accuracy_mean_action=[0.6] * 10)
    for seed in (0, 1):  # a seed whose heads never read behind a scan: no paired comparison for the row
        fake_record(table1, tmp_path, "pcrn_nclass", seed, [0.4] * 10, test_columns={"prior": [0.3] * 10} if seed else {})
    fake_record(table1, tmp_path, "planner_copy", 0, [0.7] * 10, val=0.8)
    fake_record(table1, tmp_path, "planner_copy_library", 0, [0.8] * 10, val=0.7)
    fake_record(table1, tmp_path, "lstm", 0, [0.95] * 10, val=0.95)  # not a PCRN variant
    fake_record(table1, tmp_path, "side_scan", 0, [0.5] * 10, val=0.99)  # fixed probes
    fake_record(table1, tmp_path, "random_candidates_library", 0, [0.6] * 10, val=None)
    for seed in (0, 1):
        fake_record(table1, tmp_path, "random", seed, [0.2 + 0.1 * seed] * 10)
    table1.merge(tmp_path)
    saved = json.loads((tmp_path / "table1.json").read_text())
    assert saved["best_variant"] == "planner_copy" and saved["rows"]["random"]["test_reads"] == 2
    assert saved["rows"]["random"]["accuracy_std"][0] == pytest.approx(0.0707, abs=1e-4)  # ddof=1 over 2 seeds
    text = (tmp_path / "table1.md").read_text()
    assert "(highest mean validation accuracy after 10 probes, 0.800): a choice among the greedy planner's" in text
    assert "After 10 probes >= 0.95: not met (0.700, -0.250)." in text
    # the margins over probes placed by no one: between learned heads, which may differ from row to row, or read
    # by the same library classifier on both sides
    assert "Beats side-picking scan + mirrored touch-set classifiers (fixed probes) by >= 0.15 after its last probe, " \
           "both predicted by learned heads (the two rows' heads may differ): met (+0.200" in text
    assert "Beats random candidates of the planner, named by planner_copy's library classifier (no learning) by >= " \
           "0.15 after its last probe, the same classifier ('library') reading both: met (+0.200, planner_copy's " \
           "probes, named by the library classifier alone)." in text
    assert "| random probes + PCRN-FC | learned | random | 2 | 0.250 +- 0.071 |" in text
    # #57's paired comparison: the same heads behind the policy's probes and behind its scan's, seed by seed
    assert saved["rows"]["choice_on_side_scan"]["seeds_above_prior"] == [1] * 10
    assert "gain_over_prior" not in saved["rows"]["pcrn_nclass"]
    assert ("- learned Gaussian policy started on the side-picking scan + mirrored touch sets above its reference "
            "scan in every seed, the same heads behind both, after 5 and 10 probes: met (after 5: 0.925 against 0.875, "
            "+0.050 +- 0.000, above in 2 of 2 seeds; after 10:") in text
    assert "the hybrid rule + mirrored touch sets above its reference scan in every seed, the same heads behind both, " \
           "after 5 and 10 probes: not met (after 5: 0.400 against 0.350, +0.050 +- 0.212, above in 1 of 2 seeds;" in text
    assert "the hybrid rule + mirrored touch sets by its mean action above its reference scan in every seed, the same " \
           "heads behind both, after 5 and 10 probes: met (after 5: 0.600 against 0.350, +0.250 +- " in text
    assert saved["rows"]["choice_on_side_scan"]["seeds_mean_action_above_prior"] == [2] * 10
    assert table1.gains_over_reference_scan({"random": saved["rows"]["random"]}) == [
        "- No learned policy's runs scored their heads behind their reference scan: not compared."]
    assert "Beats the LSTM at every probe count from 3 on: not met at [3, 4, 5, 6, 7, 8, 9, 10]." in text
    # records the table must not take: another test set, a row defined otherwise, a split other than test
    stale = fake_record(table1, tmp_path, "lstm", 1, [0.5] * 10, fingerprint="other")
    shutil.copytree(tmp_path / "table1_runs", tmp_path / "results" / "table1_runs")
    result = run("reproduce_table1", "--merge-only", "--out", str(tmp_path / "results"))
    assert result.returncode != 0 and "different test episodes" in result.stderr
    assert not (tmp_path / "results" / "table1.md").exists()  # nothing half-written
    stale.write_text(json.dumps(json.loads(stale.read_text()) | {"test_fingerprint": "abc", "definition": {}}))
    with pytest.raises(ValueError, match="lstm-seed1.json: made by another definition of row lstm"):
        table1.merge(tmp_path)
    stale.write_text(json.dumps(json.loads(stale.read_text()) | {"definition": table1.ROWS["lstm"].definition(),
                                                                  "split": "val"}))
    with pytest.raises(ValueError, match="lstm-seed1.json: scored the val split; the table holds test scores only"):
        table1.merge(tmp_path)


def test_merge_only_over_the_hg4_records_writes_the_ablations_page_and_leaves_the_table(tmp_path):
    """The committed hg4 records (rows whose configs are deleted) do not enter the table; they make
    docs/ablations.md, the same bytes every time: the committed page is the one the script writes."""
    table1 = script("reproduce_table1")
    out = tmp_path / "results"
    out.mkdir()
    (out / "runs").symlink_to(ROOT / "docs" / "results" / "runs")
    result = run("reproduce_table1", "--merge-only", "--out", str(out))
    assert result.returncode == 0, result.stderr[-2000:]
    assert "no record of the rows defined here yet; the table is left as it is" in result.stdout
    assert not (out / "table1.md").exists() and not (out / "table1.json").exists()
    page = (tmp_path / "ablations.md").read_text()
    assert page == (ROOT / "docs" / "ablations.md").read_text()
    assert page.startswith("# Ablations of the hg4 research\n\nGenerated by `.venv/bin/python "
                           "scripts/reproduce_table1.py --ablations`")
    assert "old protocol" in page and "(archive/README.md)" in page
    assert "`git checkout 743bddf && .venv/bin/python scripts/reproduce_table1.py --rows <old row> --seeds N" in page
    ablations, replaced = page.split("## The hg4 rows that Table 1's rows replace")
    old_rows = {json.loads(p.read_text())["row"] for p in (ROOT / "docs/results/runs").glob("*.json")}
    was = {row.was for row in table1.ROWS.values()}
    for row in old_rows:  # every hg4 row once: an ablation, or replaced by a row of the table
        assert (f"\n| `{row}` |" in ablations) == (row not in was) and (f"\n| `{row}` |" in replaced) == (row in was)
    assert ("| `centre_scan` | centre-out scan + PCRN-FC (beyond the paper) | learned | 0, 1, 2 | 0.378 +- 0.011 | "
            "0.554 +- 0.051 | 0.781 +- 0.014 | `configs/centre_scan.yaml` |") in ablations
    assert "| `planner` | greedy information-gain planner over training episodes (moved along the line and mirrored), " \
           "Bayes classifier, no learning (beyond the paper) | library | 0 |" in ablations  # 32768 poses
    assert ("| `pcrn_fc_candidates_readings_only_imitate_planner65k_final_mirror_library_namer` | mixed | 0, 1, 2 | "
            "0.382 +- 0.003 | 0.720 +- 0.035 | 0.960 +- 0.012 | `planner_copy_library`, `planner_copy_mixed` |") in replaced
    assert "`--rows pcrn_fc_candidates_readings_only_imitate_planner_final_mirror_library_namer --seeds 0 1 2` (after " \
           "`pcrn_fc_candidates_readings_only_imitate_planner_final_mirror`)" in ablations
    alone = run("reproduce_table1", "--ablations", "--out", str(out))
    assert alone.returncode == 0 and (tmp_path / "ablations.md").read_text() == page
    # the noise table too stays the hg4 research's until our model has runs made from Table 1's rows
    (out / "noise_runs").symlink_to(ROOT / "docs" / "results" / "noise_runs")
    noise = run("reproduce_noise", "--merge-only", "--out", str(out))
    assert noise.returncode == 0 and "no run made from Table 1's rows yet; noise.* left as they are" in noise.stdout
    assert set(json.loads(noise.stdout.strip().splitlines()[-1])) == {"commit", "pointnet", "dgcnn"}
    assert not (out / "noise.md").exists()
