"""Long training runs (``pytest -m slow``): a default-size Duffing Phase 1 beats the paper's table."""

import numpy as np
import pytest

pytest.importorskip("torch")

import kklcasadi as kc  # noqa: E402
from kklcasadi.evaluation.protocol import Protocol, evaluate  # noqa: E402
from kklcasadi.train import default_config, train_observer  # noqa: E402

pytestmark = pytest.mark.slow

#: The paper's Table I, Duffing row of its best method (HyperKKL_obs), noise-free SMAPE %.
PAPER_BEST = {"zero": 5.6, "constant": 21.1, "sinusoid": 22.7, "square": 21.3}


def test_duffing_phase1_and_inject_beat_the_papers_best_method(tmp_path):
    base = tmp_path / "duffing" / "autonomous"
    train_observer("duffing", "autonomous", base, config=default_config("duffing", "autonomous"), progress=False,
                   threads=1)
    train_observer("duffing", "inject", tmp_path / "duffing" / "inject")
    obs = kc.load_observer(tmp_path / "duffing" / "inject")
    protocol = Protocol(n_trials=10).noise_free()
    results = evaluate(lambda t, y, u: obs.simulate(t, y, u).xhat, obs.system, protocol)
    for r in results:
        assert np.mean(r.smape) < PAPER_BEST[r.kind], (r.kind, np.mean(r.smape))
