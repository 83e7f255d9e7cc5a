"""The library of simulated training episodes, its Bayes classifier (one update loop) and the greedy planner.

torch and numpy over hg.sim; no Lightning. Teacher files (the planner's chosen probes, for a policy to imitate) are
written and checked here too.
"""
from hg.planner.classifier import Choose, Kept, KeptWeights, LibraryClassifier, Read, belief, log_likelihood
from hg.planner.greedy import (Evaluation, GreedyPlanner, Rollouts, centre_out_scan, evaluate, expected_entropy,
                               fixed_choice, plan, random_choice, summary)
from hg.planner.library import MISS, CandidateGrid, LibraryRecipe, library_readings, readings, teacher_library
from hg.planner.teacher import SCHEMA, load_teacher, read_meta, save_teacher, teacher_meta

__all__ = ["MISS", "SCHEMA", "CandidateGrid", "Choose", "Evaluation", "GreedyPlanner", "Kept", "KeptWeights",
           "LibraryClassifier", "LibraryRecipe", "Read", "Rollouts", "belief", "centre_out_scan", "evaluate",
           "expected_entropy", "fixed_choice", "library_readings", "load_teacher", "log_likelihood", "plan",
           "random_choice", "read_meta", "readings", "save_teacher", "summary", "teacher_library", "teacher_meta"]
