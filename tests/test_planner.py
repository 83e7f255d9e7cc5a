"""hg.planner: the library classifier's posterior, the greedy planner on real probes, teacher files and their checks."""
import json
import math
import os
import subprocess
import sys
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest
import torch

from hg.planner import (MISS, CandidateGrid, GreedyPlanner, LibraryClassifier, LibraryRecipe, evaluate, load_teacher,
                        plan, read_meta, save_teacher, teacher_library, teacher_meta)
from hg.sim import PoseRegions, ProbeSimulator, Scene, SensorNoise, sample_episodes
from hg.sim.heldout import AcrossLineRegions
from hg.planner.library import readings

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "WANDB_MODE": "disabled", "OMP_NUM_THREADS": "1"}


def hand_made(noise: SensorNoise = SensorNoise(), **kwargs) -> LibraryClassifier:
    """Five library episodes (classes 0, 1, 0, 1, 0: not sorted) read by two candidates."""
    library = torch.tensor([[0.10, MISS], [0.11, 0.20], [0.10, MISS], [MISS, MISS], [MISS, 0.30]])
    return LibraryClassifier(library, torch.tensor([0, 1, 0, 1, 0]), 2, sigma=0.01, mismatch=1e-3, noise=noise,
                             probe_length=0.6, **kwargs)


def test_classifier_posterior_on_a_hand_made_library_is_the_closed_form():
    m, g = 1e-3, math.exp(-0.5)  # a touch against a miss keeps `mismatch`; 1 cm off with sigma 1 cm keeps e^-1/2
    classifier = hand_made(positions=torch.tensor([[0.1, 0.5], [0.2, -0.5], [0.3, 0.5], [-0.4, 0.0], [0.5, 1.0]]))
    assert classifier.labels.tolist() == [0, 0, 0, 1, 1]  # by class; as given through `drawn`
    assert classifier.labels[classifier.drawn].tolist() == [0, 1, 0, 1, 0]
    chosen, read = torch.tensor([[0, 1]]), torch.tensor([[0.10, MISS]])
    posterior = classifier(chosen, read).exp()[0]
    # probe 1 reads 0.10: class 0's episodes weigh 1, 1, m; class 1's e^-1/2, m
    first = np.array([2 + m, g + m])
    # probe 2 reads nothing on candidate 1: class 0's weigh 1 * 1, 1 * 1, m * m (0.30 read as a miss); class 1's
    # e^-1/2 * m (0.20 read as a miss), m * 1
    second = np.array([2 + m * m, g * m + m])
    np.testing.assert_allclose(posterior.numpy(), np.stack([first, second]) / np.array([[first.sum()], [second.sum()]]),
                               rtol=1e-6)
    # the one update loop: playing the same choices step by step gives the same numbers, to the bit
    played, looked = classifier.play(2, 1, lambda k, log_w, used: chosen[:, k], lambda k, c: read[:, k],
                                     classifier.log_posterior)
    assert played.tolist() == chosen.tolist() and torch.equal(looked, classifier(chosen, read))
    assert classifier.name(classifier.update(classifier.prior(1), chosen[:, 0], read[:, 0])).tolist() == [0]
    # a reading left out changes nothing
    ignored = classifier(chosen, read, ignore=torch.tensor([[False, True]])).exp()[0]
    torch.testing.assert_close(ignored[1], ignored[0])
    # the belief after probe 1, over positions (x across, y along the line)
    x, y = classifier.positions.T.numpy()  # in the classifier's order: by class
    belief = classifier.beliefs(chosen, read)[0, 0].numpy()
    weights = np.array([1, 1, m, g, m]) / (2 + g + 2 * m)  # classes 0 (episodes 0, 2, 4) then 1 (episodes 1, 3)
    mean_y = weights @ y
    np.testing.assert_allclose(belief, [*first / first.sum(), mean_y, np.sqrt(weights @ y ** 2 - mean_y ** 2),
                                        weights @ x, weights[x > 0].sum()], rtol=1e-5)
    # a faulty sensor's model: a miss read where the library touched keeps miss_prob, a miss where it missed 1 - rate
    noisy = hand_made(SensorNoise(miss_prob=0.1, false_contact_prob=0.1))
    log_w = noisy.update(noisy.prior(1), torch.tensor([1]), torch.tensor([MISS]))
    torch.testing.assert_close(log_w[0], torch.log(torch.tensor([0.9, 0.9, 0.1, 0.1, 0.9])))  # by class
    with pytest.raises(ValueError, match=r"no episode of class \[2\]"):
        LibraryClassifier(torch.zeros(2, 1), torch.tensor([0, 1]), 3, 0.01, 1e-3)


def test_classifier_names_as_the_recorded_library_namer_did():
    """tests/golden/golden.json holds the model's library posterior on a tiny eval rollout of the planner copy's
    config, over 64 episodes of data/planner/train65k_s10.npz's library (recorded by the library namer at 743bddf,
    re-recorded when the library began dropping copies that leave the training region: tests/test_golden.py):
    rebuilt here from the teacher's meta outside the model, the classifier reads the same probes to the same
    numbers (the golden file keeps 6 decimals)."""
    golden = json.loads((ROOT / "tests" / "golden" / "golden.json").read_text())["planner_copy"]
    regions = PoseRegions()
    labels, poses = sample_episodes(regions, "train", 8, 4, np.random.default_rng([0, 0, 0, 0]))  # episode_batch's
    assert labels.tolist() == golden["labels"]
    meta = teacher_meta([ROOT / "data" / "planner" / "train65k_s10.npz"])
    grid = CandidateGrid.from_meta(meta)
    candidates = grid.requests()
    requests = np.array(golden["eval"]["requests"])  # (8, 4, 4), each one of the candidates
    chosen = torch.from_numpy(np.abs(requests[:, :, None] - candidates).max(-1).argmin(-1))
    assert np.abs(candidates[chosen.numpy()] - requests).max() < 1e-5
    with ProbeSimulator("hg4", batch_size=1024, mode="ideal") as sim:
        recipe = LibraryRecipe.from_meta(meta, 64)
        assert not recipe.confined  # a file from before schema 2: its planner read an unconfined library
        classifier = LibraryClassifier.build(sim, regions, grid, replace(recipe, confined=True))  # as the model does
        library, library_labels, _ = teacher_library(meta, sim, regions, 4, 64)  # what the planner read
        confined, confined_labels, _ = replace(recipe, confined=True).draw(sim, regions, grid)
        read = torch.from_numpy(readings(sim, labels, poses, candidates)).gather(1, chosen)
    assert classifier.library.shape == (len(candidates), len(confined)) and sorted(confined_labels) == \
        classifier.labels.tolist()
    assert len(confined) < len(library)  # the copies its shifts and mirrors carried into held-out cells are gone
    torch.testing.assert_close(classifier(chosen, read), torch.tensor(golden["eval_named"]), atol=1e-5, rtol=0)


def test_planner_touches_more_and_names_better_than_random_candidates_on_real_probes():
    regions = PoseRegions()
    labels, poses = sample_episodes(regions, "val", 64, 4, np.random.default_rng(0))
    grid = CandidateGrid(5, 0.5, (1.0,))
    result = evaluate("hg4", labels, poses, regions, grid=grid, recipe=LibraryRecipe(512, "train", 1, True),
                      n_probes=4, probers=("planner", "fixed", "random"))
    planner, fixed, random = (result.rollouts[name] for name in ("planner", "fixed", "random"))
    assert planner.summary["touches"] > random.summary["touches"] + 0.5
    assert np.mean(planner.summary["accuracy"]) > np.mean(random.summary["accuracy"]) + 0.03
    assert (planner.chosen[:, 0] == planner.chosen[0, 0]).all()  # before any probe every episode looks alike
    assert all(len(set(row)) == 4 for row in planner.chosen.tolist())  # no fault: never a candidate twice
    assert fixed.chosen[0].tolist() == [6, 3, 9, 0] and fixed.summary["tilt_deg"] == 0  # straight, centre out
    assert result.faults is None and 512 < result.library_episodes <= 512 * 6  # with the moves and mirror images
    np.testing.assert_array_equal(planner.requests, grid.requests()[planner.chosen])


def teacher(path: Path, regions: PoseRegions = PoseRegions(), split: str = "train", noise: SensorNoise = SensorNoise(),
            grid: CandidateGrid = CandidateGrid(3, 0.5, (1.0,)), n_probes: int = 3) -> dict:
    """A teacher file of 16 episodes of `split` probing the first candidates in order."""
    labels, poses = sample_episodes(regions, split, 16, 4, np.random.default_rng(0))
    requests = np.tile(grid.requests()[:n_probes], (16, 1, 1))
    faults = np.random.default_rng(1).random((16, n_probes, 2)) if noise.miss_prob else None
    return save_teacher(path, labels, poses, requests, object_set_name="hg4", classes=("a", "b", "c", "d"),
                        regions=regions, robot="urdf/hg_probe_arm.urdf", mode="ideal", noise=noise, seed=3, grid=grid,
                        recipe=LibraryRecipe(256, "train", 1, True, seed=3), bin=0.01, faults=faults)


def test_plan_writes_a_teacher_that_loads_with_its_provenance(tmp_path):
    path = tmp_path / "t.npz"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "plan.py"), "--split", "train", "--library-split",
                           "train", "--library", "128", "--episodes", "16", "--n-probes", "3", "--places", "3",
                           "--leans", "1.0", "--seed", "4", "--save-rollouts", str(path)],
                          capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(result["planner"]["accuracy"]) == 3 and result["candidates"] == 9 and result["split"] == "train"
    loaded = load_teacher([path], object_set_name="hg4", scene=Scene(), regions=AcrossLineRegions(), n_probes=3)
    with pytest.raises(ValueError, match=r"teacher meta regions=\{'across_line'.*this run has \{'cells'"):
        load_teacher([path], object_set_name="hg4", scene=Scene(), regions=PoseRegions(), n_probes=3)
    # the bands do not depend on the evaluation seed: a run drawing other validation and test episodes may copy it
    again = load_teacher([path], object_set_name="hg4", scene=Scene(), regions=AcrossLineRegions(seed=1), n_probes=3)
    assert torch.equal(again["requests"], loaded["requests"])
    assert loaded["requests"].shape == (16, 3, 4) and loaded["faults"] is None and loaded["labels"].dtype == torch.long
    candidates = torch.from_numpy(CandidateGrid(3, 0.5, (1.0,)).requests()).float()
    assert ((loaded["requests"][:, :, None] - candidates).abs().amax(-1).amin(-1) < 1e-6).all()  # every one a candidate
    meta = teacher_meta([path])
    assert meta["schema"] == 2 and meta["confined"] and meta["objects"] == "hg4"
    assert meta["scene"] == json.loads(json.dumps(asdict(Scene())))
    assert meta["robot"] == "urdf/hg_probe_arm.urdf" and meta["mode"] == "ideal" and meta["noise"] == 0.0
    assert (meta["seed"], meta["library_seed"], meta["eval_seed"], meta["library"], meta["places"]) == (4, 4, 0, 128, 3)
    assert meta["summary"] == result["planner"] and meta["commit"]
    assert meta["planner_settings"] == result["planner_settings"] == {"prune": 20.0, "samples": 512, "refine": 3}
    bad = subprocess.run([sys.executable, str(ROOT / "scripts" / "plan.py"), "--fixed", "--n-probes", "12"],
                         capture_output=True, text=True, env=ENV, timeout=300)
    assert bad.returncode != 0 and "--fixed: the straight scan probes each of the 11 places once" in bad.stderr


def test_a_teacher_of_another_world_probe_count_or_sensor_is_refused_naming_the_field(tmp_path):
    path = tmp_path / "t.npz"
    teacher(path)
    world = {"object_set_name": "hg4", "scene": Scene(), "regions": PoseRegions(), "n_probes": 3}
    assert load_teacher([path], **world)["requests"].shape == (16, 3, 4)
    other_scene = Scene(probe_length=0.5)
    for change, message in (({"object_set_name": "other"}, "teacher meta objects='hg4', this run has 'other'"),
                            ({"regions": PoseRegions(seed=1)}, "teacher meta eval_seed=0, this run has 1"),
                            ({"regions": AcrossLineRegions()}, r"teacher meta regions=\{'cells'"),
                            ({"scene": other_scene, "regions": PoseRegions(other_scene)}, "teacher meta scene="),
                            ({"n_probes": 4}, r"expected \(16, 4, 4\) \(n_probes=4\)"),
                            ({"noise": SensorNoise(miss_prob=0.1, false_contact_prob=0.1)},
                             r"planned with sensor faults at rate 0.0 \(teacher meta noise\), this run's rate is 0.1")):
        with pytest.raises(ValueError, match=f"{path}: .*{message}"):
            load_teacher([path], **(world | change))
    noisy = tmp_path / "noisy.npz"
    teacher(noisy, noise=SensorNoise(miss_prob=0.2, false_contact_prob=0.2))
    loaded = load_teacher([noisy], **world, noise=SensorNoise(miss_prob=0.2, false_contact_prob=0.2))
    assert loaded["faults"].shape == (16, 3, 2)
    with pytest.raises(ValueError, match=f"{noisy}: planned with sensor faults at rate 0.2 .*rate is 0.0: write a "
                                         "teacher with scripts/plan.py --noise 0.0"):
        load_teacher([noisy], **world)
    with pytest.raises(ValueError, match="one rate"):
        teacher(tmp_path / "blurred.npz", noise=SensorNoise(position_std=0.01))
    other = tmp_path / "other.npz"
    teacher(other, grid=CandidateGrid(5, 0.5, (1.0,)))
    with pytest.raises(ValueError, match=rf"{other}: teacher meta \['places'\] differ from {path}'s"):
        teacher_meta([path, other])
    newer = tmp_path / "newer.npz"
    with np.load(path) as f:
        np.savez(newer, **{k: f[k] for k in f.files} | {"meta": np.array(json.dumps(read_meta(path) | {"schema": 3}))})
    with pytest.raises(ValueError, match=f"{newer}: teacher meta schema=3, this code reads schema <= 2"):
        teacher_meta([newer])
    with pytest.raises(FileNotFoundError, match="nope.npz: teacher file not found"):
        load_teacher([tmp_path / "nope.npz"], **world)


def test_a_teacher_pose_outside_the_training_region_is_refused(tmp_path):
    path = tmp_path / "val.npz"
    teacher(path, split="val")
    with pytest.raises(ValueError, match=f"{path}: 16 of 16 poses lie outside the training region"):
        load_teacher([path], object_set_name="hg4", scene=Scene(), regions=PoseRegions(), n_probes=3)


def test_old_teacher_files_load_as_schema_0_checked_on_what_they_carry():
    old, noisy = ROOT / "data" / "planner" / "train_s10.npz", ROOT / "data" / "planner" / "train_s10_noise10.npz"
    world = {"object_set_name": "hg4", "scene": Scene(), "regions": PoseRegions(), "n_probes": 10}
    loaded = load_teacher([old], **world)
    assert loaded["requests"].shape == (4096, 10, 4) and loaded["faults"] is None
    meta = teacher_meta([old])
    assert meta["schema"] == 0 and meta["library_seed"] == 10 and meta["along_leans"] == [] and "scene" not in meta
    assert LibraryRecipe.from_meta(meta) == LibraryRecipe(32768, "train", 5, True, 10, 0.005, 1e-3, confined=False)
    assert CandidateGrid.from_meta(meta) == CandidateGrid()
    rate = SensorNoise(miss_prob=0.1, false_contact_prob=0.1)
    assert load_teacher([noisy], **world, noise=rate)["faults"].shape == (3072, 10, 2)
    with pytest.raises(ValueError, match=f"{old}: planned under noise without its faults"):
        load_teacher([old], **world, noise=rate)
    with pytest.raises(ValueError, match=f"{old}: teacher meta objects='hg4', this run has 'other'"):
        load_teacher([old], **(world | {"object_set_name": "other"}))


def synthetic(n_library: int = 400, n_candidates: int = 12,
              seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A random library of 3 classes (readings in [0, 0.3] m or MISS), with no symmetry to make candidates tie, and
    24 episodes reading like its episodes give or take 2 mm."""
    rng = np.random.default_rng(seed)
    library = np.where(rng.random((n_library, n_candidates)) < 0.4, MISS,
                       rng.uniform(0, 0.3, (n_library, n_candidates)))
    query = library[rng.integers(n_library, size=24)]
    query = np.where(query == MISS, MISS, query + rng.normal(0, 0.002, query.shape))
    return (torch.from_numpy(library).float(), torch.from_numpy(rng.integers(3, size=n_library)),
            torch.from_numpy(query).float())


@pytest.mark.parametrize("noise", [SensorNoise(), SensorNoise(miss_prob=0.1, false_contact_prob=0.05)])
def test_a_pruned_classifier_keeps_the_exact_log_weights_and_drops_only_those_below_the_margin(noise):
    library, labels, query = synthetic()
    exact = LibraryClassifier(library, labels, 3, sigma=0.01, mismatch=1e-3, noise=noise, probe_length=0.6)
    pruned = LibraryClassifier(library, labels, 3, sigma=0.01, mismatch=1e-3, noise=noise, probe_length=0.6,
                               prune=6.0)
    chosen = torch.stack([torch.randperm(12, generator=torch.Generator().manual_seed(i))[:5] for i in range(24)])
    read = query.gather(1, chosen)
    log_w, kept = exact.prior(24), pruned.prior(24)
    dropped = [0] * 24
    for k in range(5):
        exact.update(log_w, chosen[:, k], read[:, k])
        before = [None if state is None else state.index for state in kept]
        pruned.update(kept, chosen[:, k], read[:, k])
        for b, state in enumerate(kept):
            # the kept episodes' log weights are the exact classifier's, to the bit (the same operations)
            np.testing.assert_array_equal(state.log_w, log_w[b, state.index].numpy())
            gone = np.setdiff1d(np.arange(len(labels)) if before[b] is None else before[b], state.index)
            assert (log_w[b, gone] < log_w[b, state.index].max() - 6.0).all()  # dropped: below the margin then
            dropped[b] += len(gone)
    assert sum(dropped) > 0
    # a margin nothing falls below: the class posterior and the names are the exact classifier's
    positions = torch.rand(len(labels), 2, generator=torch.Generator().manual_seed(0))
    exact = LibraryClassifier(library, labels, 3, sigma=0.01, mismatch=1e-3, noise=noise, probe_length=0.6,
                              positions=positions)
    lossless = LibraryClassifier(library, labels, 3, sigma=0.01, mismatch=1e-3, noise=noise, probe_length=0.6,
                                 positions=positions, prune=1e9)
    torch.testing.assert_close(lossless(chosen, read), exact(chosen, read), rtol=0, atol=1e-5)
    # (the spread along the line, a difference of squares in float32, rounds to within 1e-4)
    torch.testing.assert_close(lossless.beliefs(chosen, read), exact.beliefs(chosen, read), rtol=0, atol=1e-4)
    with pytest.raises(ValueError, match="prune=0.0 must be > 0"):
        LibraryClassifier(library, labels, 3, sigma=0.01, mismatch=1e-3, prune=0.0)


@pytest.mark.parametrize("samples, refine", [(10 ** 6, 1), (2, 12)])
def test_a_lossless_pruned_planner_chooses_as_the_exact_planner(samples, refine):
    """Nothing pruned, and either every kept episode weighed (no draws) or two draws per class ranking the candidates
    and every candidate refined over every kept episode: the choices and names are the exact planner's (a sigma of 3 cm
    keeps the posteriors short of certainty, where candidates leaving no entropy would tie)."""
    library, labels, query = synthetic()
    exact = LibraryClassifier(library, labels, 3, sigma=0.03, mismatch=1e-3)
    pruned = LibraryClassifier(library, labels, 3, sigma=0.03, mismatch=1e-3, prune=1e9)
    chosen, named = plan(exact, query, 6, GreedyPlanner(exact, 0.01))
    fast_chosen, fast_named = plan(pruned, query, 6, GreedyPlanner(pruned, 0.01, samples, refine))
    np.testing.assert_array_equal(fast_chosen, chosen)
    np.testing.assert_array_equal(fast_named, named)
    assert len(set(chosen[:, 1].tolist())) > 1  # the choices depend on the readings


def test_the_planners_draws_keep_each_class_weight_and_approach_the_exact_cell_sums():
    """hg.planner.kernels.sampled_mass: a class with more kept episodes than samples is drawn at every 1/samples of
    its weight, so its cells still sum to its weight, and draws fall on episodes in proportion to theirs; a class with
    fewer is summed whole, as candidate_mass sums it."""
    from hg.planner.kernels import candidate_mass, class_sums, sampled_mass
    rng = np.random.default_rng(0)
    n_candidates, size = 3, 8  # cells per candidate
    columns = rng.integers(0, size, (n_candidates, 1000)).astype(np.int32)
    codes = np.ascontiguousarray(columns.T + np.arange(n_candidates, dtype=np.int32) * size)
    index = np.sort(rng.choice(1000, 700, replace=False)).astype(np.int32)
    weight = rng.random(700).astype(np.float32) ** 4  # uneven
    ends = np.array([600, 700])  # class 0: 600 kept episodes, drawn; class 1: 100, summed whole
    mass = class_sums(weight, ends)
    np.testing.assert_allclose(mass, [weight[:600].sum(), weight[600:].sum()], rtol=1e-6)
    exact = candidate_mass(columns, np.arange(n_candidates), index, weight, size)
    error = {}
    for samples in (32, 512):
        drawn, any_drawn = sampled_mass(codes, index, weight, ends, mass, samples, n_candidates * size)
        assert any_drawn
        assert drawn.sum() == pytest.approx(n_candidates * mass.sum())
        error[samples] = np.abs(drawn - exact).sum() / exact.sum()
    # the cells' weights by draws come closer to the exact sums with more draws (0.25, then 0.03, of the weight)
    assert 0 < error[512] < 0.05 < error[32]
    # class 1 alone, fewer episodes than samples: summed whole, exactly
    alone, any_drawn = sampled_mass(codes, index[600:], weight[600:], np.array([0, 100]), class_sums(
        weight[600:], np.array([0, 100])), 128, n_candidates * size)
    assert not any_drawn
    np.testing.assert_allclose(alone, candidate_mass(columns, np.arange(n_candidates), index[600:], weight[600:], size))
