"""Ablations over seeds (eval/report/seed_runs.py): means, spreads and when a variant may be called ahead."""

from __future__ import annotations

import numpy as np
import pytest

from eval.report.seed_runs import MIN_SEEDS, seed_mean_ap, seed_paired_difference, seed_verdict
from eval.report.tables import ablation_comparison_table
from eval.stats import TIE


def _result(per_scene_ap: list[float], first_index: int = 0) -> dict:
    """An AP result with the keys seed_runs reads: per-scene figures and the stored scene index."""
    values = np.asarray(per_scene_ap, dtype=float)
    per_scene = {m: (values * f).tolist() for m, f in (("AP", 1.0), ("AP0.8", 0.5), ("AP0.4", 1.2),
                                                       ("top1_AP", 1.1))}
    return {"AP": float(values.mean()), "per_scene": per_scene,
            "scenes": [{"index": first_index + i} for i in range(len(values))]}


def test_seed_mean_is_the_mean_of_the_seeds_on_their_shared_scenes():
    a, b = _result([10.0, 20.0, 30.0]), _result([40.0, 50.0], first_index=1)  # b lacks scene 0
    mean = seed_mean_ap([a, b], [0, 1])
    assert [s["index"] for s in mean["scenes"]] == [1, 2] and mean["num_scenes"] == 2
    assert mean["per_scene"]["AP"] == pytest.approx([30.0, 40.0])
    assert mean["AP"] == pytest.approx(35.0) and mean["AP0.8"] == pytest.approx(17.5)
    # per-seed means on the shared scenes are 25 and 45: their std (ddof 1) is 20 / sqrt(2)
    assert mean["seed_std"]["AP"] == pytest.approx(20.0 / np.sqrt(2.0))
    assert mean["intervals"]["AP"]["low"] <= 35.0 <= mean["intervals"]["AP"]["high"]
    assert seed_mean_ap([a], [0])["seed_std"]["AP"] is None
    with pytest.raises(ValueError, match="one AP result per seed"):
        seed_mean_ap([a], [0, 1])


def _seeds(base: np.ndarray, shifts: list[float]) -> dict[int, dict]:
    return {seed: _result((base + shift).tolist()) for seed, shift in enumerate(shifts)}


def test_a_variant_is_ahead_only_when_every_seed_agrees_and_the_scenes_resolve_it():
    base = np.random.default_rng(0).uniform(20, 60, 40)
    reference = _seeds(base, [0.0, 0.0, 0.0])
    better = seed_paired_difference(_seeds(base, [5.0, 4.0, 6.0]), reference)
    assert better["seeds"] == [0, 1, 2] and better["mean"] == pytest.approx(5.0) and better["std"] == pytest.approx(1.0)
    assert better["pooled"]["low"] > 0 and better["direction"] == 1
    assert seed_verdict(better, "variant", "reference") == "variant ahead"
    worse = seed_paired_difference(_seeds(base, [-3.0, -2.0, -4.0]), reference)
    assert seed_verdict(worse, "variant", "reference") == "reference ahead"
    # the seed mean is +4, resolved over scenes, but one seed says the opposite: no claim
    split = seed_paired_difference(_seeds(base, [7.0, 7.0, -2.0]), reference)
    assert split["pooled"]["low"] > 0 and split["direction"] == 0
    assert seed_verdict(split, "variant", "reference") == TIE
    # two seeds, however clear, are fewer than a claim needs
    two = seed_paired_difference(_seeds(base, [5.0, 5.0]), reference)
    assert two["seeds"] == [0, 1] and seed_verdict(two, "v", "r") == f"{TIE} (only 2 of the {MIN_SEEDS} seeds a claim needs)"
    assert seed_paired_difference({5: reference[0]}, reference) is None  # no seed in common


def test_the_comparison_table_reads_each_variant_against_its_baseline_of_the_same_seed():
    base = np.random.default_rng(1).uniform(20, 60, 30)

    def row(name: str, shifts: list[float], baseline: str | None = "reference", test: str = "data/test") -> dict:
        runs = [{"seed": s, "ap": r} for s, r in _seeds(base, shifts).items()]
        return {"name": name, "kind": "trained", "description": name, "runs": runs, "baseline": baseline,
                "test_data": test, "ap": seed_mean_ap([r["ap"] for r in runs], [r["seed"] for r in runs])}

    table = ablation_comparison_table([
        row("reference", [0.0, 1.0, 2.0], baseline=None), row("wider", [3.0, 4.0, 5.0]),
        row("noisy", [3.0, -1.0, 2.0]),
        # a pair on its own split: read against its own baseline, not the reference
        row("sparse", [10.0, 10.0, 10.0], baseline=None, test="data/test8k"),
        row("dense", [8.0, 9.0, 7.0], baseline="sparse", test="data/test8k"),
        # a baseline on another split is not paired scene by scene
        row("misplaced", [5.0, 5.0, 5.0], baseline="reference", test="data/test8k")])
    lines = {line.split(" | ")[0].lstrip("| "): line for line in table.splitlines()[2:]}
    assert "| reference | 3 | +3.00 ± 0.00 |" in lines["wider"] and lines["wider"].endswith("| wider ahead |")
    assert "0: +3.00, 1: -2.00, 2: +0.00" in lines["noisy"] and lines["noisy"].endswith(f"| {TIE} |")
    assert "| sparse | 3 | -2.00 ± 1.00 |" in lines["dense"] and lines["dense"].endswith("| sparse ahead |")
    assert "not paired: tested on data/test8k, its baseline on data/test" in lines["misplaced"]
    assert "reference" not in lines and "sparse" not in lines  # baselines have no row of their own
    # a row stored before baselines existed is read against the reference
    old = row("old", [1.0, 2.0, 3.0])
    del old["baseline"], old["test_data"]
    reference = row("reference", [0.0, 1.0, 2.0], baseline=None)
    del reference["test_data"]
    assert "| old | reference | 3 | +1.00 ± 0.00 |" in ablation_comparison_table([reference, old])
