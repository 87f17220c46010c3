"""Aggregation of a fake sweep: means and standard errors over seeds."""

import json
import math

import numpy as np
import pytest

from tnf.errors import TnfError
from tnf.eval.aggregate import aggregate, find_results, load_results, mean_se, over_seeds

SSIM = {"T-N": [0.97, 0.98, 0.99], "Lee": [0.60, 0.70, 0.65], "Cycle": [0.50, 0.52, 0.60]}
SIM_ACC = [80.0, 85.0, 90.0]  # the same in every generator's job of a seed
AUG_ACC = {"T-N": [95.0, 96.0, 100.0], "Lee": [82.0, 84.0, 86.0], "Cycle": [70.0, 80.0, 75.0]}


def _run(method: str, seed: int) -> dict:
    s = SSIM[method][seed]
    return {
        "schema": 1,
        "table": "main",
        "method": method,
        "seed": seed,
        "model": f"{method}-{seed}",
        "image": {
            "novel_view": {
                method: {"ssim": s, "mse": 1000 * (1 - s), "n": 10, "per_object": {"ball": {"ssim": s, "mse": 1.0}}},
                "BG": {"ssim": 0.9 + 0.01 * seed, "mse": 60.0, "n": 10},
            }
        },
        "accuracy": {"Sim": SIM_ACC[seed], f"Sim + {method}": AUG_ACC[method][seed]},
    }


def _se(v):
    return float(np.std(v, ddof=1) / math.sqrt(len(v)))


def test_mean_se_matches_numpy():
    st = mean_se([1.0, 2.0, 4.0])
    assert st.mean == pytest.approx(7 / 3) and st.se == pytest.approx(_se([1, 2, 4])) and st.n == 3
    assert mean_se([5.0]).se == 0.0


def test_same_seed_values_count_once():
    st = over_seeds([(0, 1.0), (0, 3.0), (1, 4.0)])  # seed 0 averages to 2
    assert st.n == 2 and st.mean == pytest.approx(3.0) and st.se == pytest.approx(_se([2, 4]))


def test_fake_sweep_aggregates_to_known_means_and_standard_errors(tmp_path):
    for job, (method, seed) in enumerate((m, s) for m in SSIM for s in range(3)):
        d = tmp_path / "sweep" / str(job)
        d.mkdir(parents=True)
        (d / "results.json").write_text(json.dumps(_run(method, seed)))
    files = find_results(tmp_path / "sweep")
    assert len(files) == 9
    t = aggregate(load_results(files))["main"]
    assert t.methods == ["T-N", "Lee", "Cycle"]
    for method, vals in SSIM.items():
        st = t.image[("novel_view", method)]["ssim"]
        assert st.mean == pytest.approx(np.mean(vals)) and st.se == pytest.approx(_se(vals)) and st.n == 3
        mse = t.image[("novel_view", method)]["mse"]
        assert mse.mean == pytest.approx(1000 * (1 - np.mean(vals)))
        acc = t.accuracy[f"Sim + {method}"]
        assert acc.mean == pytest.approx(np.mean(AUG_ACC[method])) and acc.se == pytest.approx(_se(AUG_ACC[method]))
        assert t.per_object[("novel_view", method)]["ball"].mean == pytest.approx(np.mean(vals))
    # Sim and BG come from all 9 jobs but each seed counts once: 3 seeds
    assert t.accuracy["Sim"].n == 3 and t.accuracy["Sim"].se == pytest.approx(_se(SIM_ACC))
    bg = t.image[("novel_view", "BG")]["ssim"]
    assert bg.n == 3 and bg.mean == pytest.approx(0.91)


def test_bad_results_files_are_refused(tmp_path):
    (tmp_path / "results.json").write_text(json.dumps({"hello": 1}))
    with pytest.raises(TnfError, match="not a tnf evaluate results file"):
        load_results(find_results(tmp_path))
    with pytest.raises(TnfError, match="not found"):
        find_results(tmp_path / "missing")
