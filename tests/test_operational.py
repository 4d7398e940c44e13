"""Operational decoders: rollouts, whitening fold, torch/CasADi agreement, and the gain from noise-aware data."""

from __future__ import annotations

from dataclasses import replace

import casadi as ca
import numpy as np
import pytest

torch = pytest.importorskip("torch")

import kklcasadi as kc  # noqa: E402
from kklcasadi.model.operational import OperationalData, operational_data  # noqa: E402
from kklcasadi.model.variants import bankdecoder as bd  # noqa: E402
from kklcasadi.model.variants import filterbank as fb  # noqa: E402
from kklcasadi.nets.specs import DECODER  # noqa: E402
from kklcasadi.plant.runs import RolloutConfig, rollouts  # noqa: E402
from kklcasadi.train.config import LoopConfig  # noqa: E402
from kklcasadi.train.decoder import DecoderConfig, fit_bank_decoder, fold_whitening, torch_decoder  # noqa: E402
from kklcasadi.train.nets import MLP  # noqa: E402

#: The benchmark's input kinds (the runs' default families are broader).
BENCH = ("zero", "constant", "sinusoid", "square")


def _bank() -> fb.FilterBank:
    return fb.FilterBank.design(1, 1, [0.5, 2.0, 6.0], [1.0], clock=0.5)


def test_rollouts_cycle_kinds_and_carry_noise() -> None:
    plant = kc.systems.get("linear")
    cfg = RolloutConfig(n_traj=8, T=4.0, kinds=BENCH, regime="train", noise_range=(1.0, 1.0))
    noise = {"process_std": 0.0, "measurement_std": 0.1}
    batch = rollouts(plant, cfg, seed=3, **noise)
    assert batch.x.shape == (8, 80, 2) and batch.y.shape == (8, 80, 1) and batch.u.shape == (8, 80, 1)
    np.testing.assert_array_equal(batch.u[0], 0.0)                  # zero, constant, sinusoid, square, ...
    assert np.ptp(batch.u[1]) == 0.0 and abs(batch.u[1, 0, 0]) > 0
    assert np.unique(np.abs(batch.u[3])).size <= 2
    resid = batch.y[..., 0] - batch.x[..., 0]                         # y = x1 for the linear plant
    assert 0.08 < resid.std() < 0.12
    again = rollouts(plant, cfg, seed=3, **noise)
    np.testing.assert_array_equal(again.y, batch.y)
    assert not np.array_equal(rollouts(plant, cfg, seed=4, **noise).y, batch.y)


@pytest.mark.parametrize("skip", [False, True])
def test_fold_whitening_gives_the_same_map(skip: bool) -> None:
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    mlp = MLP((4, 9, 2), skip=skip).to(torch.float64)
    if skip:
        with torch.no_grad():
            mlp.skip.copy_(torch.as_tensor(rng.normal(size=(2, 4))))
    arrays = mlp.to_arrays(DECODER)
    mean, white = rng.normal(size=4), rng.normal(size=(4, 4))
    folded = fold_whitening(arrays, mean, white)
    f = rng.normal(size=(30, 4))
    ref = mlp(torch.as_tensor((f - mean) @ white.T)).detach().numpy()
    got = MLP.from_arrays(folded, DECODER, mlp.spec)(torch.as_tensor(f)).detach().numpy()
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
    arrays[f"{DECODER}/in_std"] = np.full(4, 2.0)
    with pytest.raises(ValueError, match="in_std = 1"):
        fold_whitening(arrays, mean, white)


@pytest.mark.parametrize("scale, skip", [((0.0, 0.0), False), ((0.0, 0.02), False), ((0.0, 0.02), True)])
def test_torch_and_casadi_decoders_agree(scale: tuple[float, float], skip: bool) -> None:
    bank = _bank()
    rng = np.random.default_rng(1)
    torch.manual_seed(1)
    d = bank.nz + 2
    mlp = MLP((d, 16, 16, 2), skip=skip).to(torch.float64)
    mlp.set_normalisation(rng.normal(size=d), rng.uniform(0.5, 2, d), rng.normal(size=2), rng.uniform(0.5, 2, 2))
    if skip:
        with torch.no_grad():
            mlp.skip.copy_(torch.as_tensor(rng.normal(size=(2, d))))
    arrays = {**mlp.to_arrays(DECODER), bd.ASINH_SCALE: np.array(scale), **fb.bank_arrays(bank)}
    spec = bd.DecoderSpec(mlp.spec)
    dec_t = torch_decoder(spec, arrays)
    dec_c = bd.decoder_function(spec, arrays)
    feats = rng.normal(size=(7, d))
    parts = (feats[:, :bank.nz], feats[:, bank.nz:bank.nz + 1], feats[:, -1:])
    np.testing.assert_allclose(bd.decode(spec, arrays, *parts),
                               dec_t(*(torch.as_tensor(a) for a in parts)).detach().numpy(), rtol=1e-12, atol=1e-12)
    for _ in range(5):
        f = rng.normal(size=d)
        ft = torch.tensor(f, requires_grad=True)
        xt = dec_t(ft[:bank.nz], ft[bank.nz:bank.nz + 1], ft[-1:])
        jt = np.stack([torch.autograd.grad(xt[i], ft, retain_graph=True)[0].numpy() for i in range(2)])
        z, y, u = f[:bank.nz], f[bank.nz:bank.nz + 1], f[-1:]
        xc = np.asarray(dec_c(z, y, u)).ravel()
        zs, ys, us = ca.MX.sym("z", bank.nz), ca.MX.sym("y", 1), ca.MX.sym("u", 1)
        jac = ca.Function("j", [zs, ys, us], [ca.jacobian(dec_c(zs, ys, us), ca.vertcat(zs, ys, us))])
        np.testing.assert_allclose(xc, xt.detach().numpy(), rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(np.asarray(jac(z, y, u)), jt, rtol=1e-10, atol=1e-10)


def test_a_skip_decoder_starts_as_the_plain_one_and_fits_its_linear_path() -> None:
    """With ``skip`` the layers start from the same draw as without it and the linear path from zero (a
    vanishing learning rate leaves both there); a real fit moves the path, and the card records it."""
    torch.set_num_threads(1)
    plant = kc.systems.get("linear")
    bank = _bank()
    data = OperationalData.from_runs(bank, rollouts(plant, RolloutConfig(n_traj=6, T=4.0), seed=2), RolloutConfig())
    loop = LoopConfig(epochs=1, batch_size=64, lr=1e-12, val_fraction=0.1)
    fits = {skip: fit_bank_decoder(bank, data, DecoderConfig(hidden=(8,), skip=skip, dtype="float64", loop=loop),
                                   seed=3) for skip in (False, True)}
    assert fits[True].spec.mlp.to_card() == {"sizes": [bank.nz + 2, 8, 2], "activation": "tanh", "skip": True}
    assert "skip" not in fits[False].spec.mlp.to_card() and f"{DECODER}/Wskip" not in fits[False].arrays
    np.testing.assert_allclose(fits[True].arrays[f"{DECODER}/W0"], fits[False].arrays[f"{DECODER}/W0"], atol=1e-9)
    assert np.abs(fits[True].arrays[f"{DECODER}/Wskip"]).max() < 1e-9
    trained = fit_bank_decoder(bank, data, DecoderConfig(hidden=(8,), skip=True, dtype="float64",
                                                         loop=replace(loop, epochs=3, lr=1e-2)), seed=3)
    assert np.abs(trained.arrays[f"{DECODER}/Wskip"]).max() > 1e-3
    assert np.isfinite(bd.decode(trained.spec, trained.arrays, data.z, data.y, data.u)).all()
    with pytest.raises(TypeError, match="skip"):
        DecoderConfig(skip=1)
    for weight in (0.0, -0.5, float("nan")):          # the SMAPE term's weight: a number > 0
        with pytest.raises(ValueError, match=r"^smape_weight: expected a finite number > 0, received "):
            DecoderConfig(loss="mse+smape", smape_weight=weight)


def test_operational_decoder_beats_noise_free_one_on_noisy_runs() -> None:
    """A decoder fitted on noisy rollouts has lower error on held-out noisy rollouts than one fitted noise-free."""
    torch.set_num_threads(1)
    plant = kc.systems.get("linear")
    bank = _bank()
    dec = DecoderConfig(hidden=(32, 32), loop=LoopConfig(epochs=12, batch_size=256, lr=3e-3, schedule="cosine",
                                                         val_fraction=0.1), dtype="float64")
    cfg = RolloutConfig(n_traj=48, T=10.0, kinds=BENCH, regime="train", noise_range=(1.0, 1.0))
    test = rollouts(plant, cfg, seed=99)
    errs = {}
    for label, std in (("noisy", 0.1), ("clean", 0.0)):
        data = operational_data(plant, bank, cfg, 5, dt=0.05, measurement_std=std, process_std=std)
        fit = fit_bank_decoder(bank, data, dec, seed=0)
        xhat = bd.estimate(fit.spec, fit.arrays, test.y, test.u, 0.05)
        errs[label] = float(np.mean((xhat - test.x) ** 2))
    assert errs["noisy"] < 0.8 * errs["clean"], errs


def test_asinh_fit_records_scale_and_domain() -> None:
    torch.set_num_threads(1)
    plant = kc.systems.get("linear")
    dec = DecoderConfig(hidden=(8,), asinh_scale=(0.0, 0.05),
                        loop=LoopConfig(epochs=1, batch_size=64, val_fraction=0.1), dtype="float64")
    data = OperationalData.from_runs(_bank(), rollouts(plant, RolloutConfig(n_traj=4, T=2.0), seed=1),
                                     RolloutConfig())
    fit = fit_bank_decoder(_bank(), data, dec)
    np.testing.assert_array_equal(fit.arrays[bd.ASINH_SCALE], [0.0, 0.05])
    assert fit.spec.mlp.to_card() == {"sizes": [_bank().nz + 2, 8, 2], "activation": "tanh"}
    lo, hi = np.array(fit.domain["x_p0.1"]), np.array(fit.domain["x_p99.9"])
    assert np.all(lo < hi)
    with pytest.raises(ValueError, match="asinh_scale"):
        fit_bank_decoder(_bank(), data, DecoderConfig(asinh_scale=(0.0,)))


def test_input_filters_and_clock_lower_the_error_under_inputs() -> None:
    """Lever 2: a bank with input filters and a clock beats an output-only bank on forced noisy runs."""
    torch.set_num_threads(1)
    plant = kc.systems.get("linear")
    dec = DecoderConfig(hidden=(32, 32), loop=LoopConfig(epochs=12, batch_size=256, lr=3e-3, schedule="cosine",
                                                         val_fraction=0.1), dtype="float64")
    kinds = ("constant", "square")
    sampling = RolloutConfig()           # every sample over the first 5 s, every other one after
    train = rollouts(plant, RolloutConfig(n_traj=48, T=10.0, kinds=kinds, regime="train"), seed=5)
    test = rollouts(plant, RolloutConfig(n_traj=32, T=10.0, kinds=kinds, regime="train"), seed=99)
    errs = {}
    for label, bank in (("y only", fb.FilterBank.design(1, 1, [0.5, 2.0, 6.0])), ("y, u and clock", _bank())):
        fit = fit_bank_decoder(bank, OperationalData.from_runs(bank, train, sampling), dec, seed=0)
        errs[label] = float(np.mean((bd.estimate(fit.spec, fit.arrays, test.y, test.u, 0.05) - test.x) ** 2))
    assert errs["y, u and clock"] < 0.8 * errs["y only"], errs


def _plant(name: str, rhs, box) -> kc.System:
    x, u = ca.SX.sym("x", len(box)), ca.SX.sym("u", 1)
    return kc.System(name, x, u, rhs(x, u), x[0], box)


def test_runs_that_escape_are_cut_there_and_counted() -> None:
    """xdot = x: a run from x0 > 0.5 leaves the box [-1, 1] scaled by 2 about 0 before t = 1 s; none of its
    samples from there on is used, and rollouts() drops such runs."""
    plant = _plant("grow", lambda x, u: ca.vertcat(x[0]), [[-1.0, 1.0]])
    cfg = RolloutConfig(n_traj=20, T=2.0, kinds=("zero",), escape_scale=2.0, sample_period=0.05, dense_time=0.0)
    data = operational_data(plant, fb.FilterBank.design(1, 1, [1.0]), cfg, 0, dt=0.05, measurement_std=0.0)
    x0 = plant.sample_box(20, 0)[:, 0]
    escapes = np.abs(x0) * np.exp(1.95) > 2.0                      # leaves |x| <= 2 within the horizon
    assert data.record["cut"] == int(escapes.sum()) > 0 and data.record["failed"] == 0
    assert np.all(np.abs(data.x) <= 2.0)
    kept_per_run = np.minimum(40, np.floor(np.log(2.0 / np.abs(x0)) / 0.05) + 1).astype(int)
    assert abs(len(data) - kept_per_run.sum()) <= 20              # up to one boundary sample per run
    runs = rollouts(plant, cfg, 0, measurement_std=0.0, process_std=0.0)
    assert len(runs) == int((~escapes).sum())


@pytest.mark.parametrize("dt", [0.05, 0.01, 0.004])
def test_the_budget_counts_seconds_not_samples(dt: float) -> None:
    """The decoder's samples sit at fixed times: a run of 10 s gives 100 + 50 samples at every dt."""
    plant = kc.systems.get("linear")
    cfg = RolloutConfig(n_traj=3, T=10.0, kinds=("sinusoid",))
    data = operational_data(plant, _bank(), cfg, 1, dt=dt, measurement_std=0.1, process_std=0.1)
    assert data.record["samples"] == len(data) == 3 * 150
    assert data.record["simulated_s"] == 30.0
    assert data.record["substeps"] == max(1, int(np.ceil(dt * np.sqrt(2.0) / 0.05)))


def test_process_noise_per_state_and_a_range_of_noise_levels() -> None:
    """xdot = (0, 0) with process noise only on x2: x1 stays at x0, x2 wanders; the measurement noise of
    each run is the nominal one times a factor within noise_range."""
    plant = _plant("still", lambda x, u: ca.vertcat(0 * x[0], 0 * x[1]), [[-1.0, 1.0], [-1.0, 1.0]])
    cfg = RolloutConfig(n_traj=40, T=5.0, kinds=("zero",), noise_range=(0.5, 2.0), chunk=10)
    runs = rollouts(plant, cfg, 2, measurement_std=0.1, process_std=(0.0, 0.4))
    np.testing.assert_array_equal(runs.x[:, :, 0], runs.x[:, :1, 0] * np.ones((1, runs.t.size)))
    steps = np.diff(runs.x[:, :, 1], axis=1)
    assert np.all(steps.std(axis=1) > 0)
    stds = (runs.y[..., 0] - runs.x[..., 0]).std(axis=1) / 0.1
    assert 0.45 < stds.min() < 0.8 and 1.4 < stds.max() < 2.1
    data = operational_data(plant, _bank(), cfg, 2, dt=0.05, measurement_std=0.1, process_std=(0.0, 0.4))
    lo, hi = data.record["measurement_factor_range"]
    assert 0.5 <= lo < hi <= 2.0
    with pytest.raises(ValueError, match="noise_range"):
        RolloutConfig(noise_range=(2.0, 1.0))


def test_the_broad_families_and_the_wide_regime() -> None:
    """multisine stays within its amplitude, feedback and pd are laws of the noisy y within -2..2,
    and the wide regime reaches the ood amplitudes."""
    from kklcasadi.plant.runs import FAMILIES

    plant = kc.systems.get("duffing")
    cfg = RolloutConfig(n_traj=60, T=20.0, kinds=FAMILIES, regime="wide", substeps=4, chunk=25)
    runs = rollouts(plant, cfg, 4, measurement_std=0.05, process_std=0.05)
    assert len(runs) == 60
    kinds = np.array([FAMILIES[i % len(FAMILIES)] for i in range(60)])
    amp = np.abs(runs.u).max(axis=(1, 2))
    assert np.all(amp[kinds == "multisine"] <= 2.0) and np.ptp(runs.u[kinds == "multisine"], axis=1).min() > 0
    assert amp[kinds == "constant"].max() > 1.0                        # beyond the train range [-1, 1]
    loop = np.flatnonzero(np.isin(kinds, ["feedback", "pd"]))
    assert np.all(amp[loop] <= 2.0 + 1e-12) and np.all(amp[loop] > 0)
    # u_k depends on y_k through the law: its held value changes only where y_k moves it (not a fixed signal)
    assert all(np.unique(runs.u[i, :, 0]).size > 50 for i in loop)
    with pytest.raises(ValueError, match="kinds"):
        RolloutConfig(kinds=("chirp",))
    assert "pd" not in RolloutConfig().kinds                           # a family to ask for, not a default
    with pytest.raises(ValueError, match="regime"):
        RolloutConfig(regime="huge")


@pytest.mark.parametrize("scale", [1.5, (0.8, 1.6)])
def test_an_input_scale_scales_each_runs_input(scale) -> None:
    """Open-loop runs take the same inputs times their factor, the laws a limit times it; the factors of a
    range are log-uniform draws within it; the card's ranges stretch with it."""
    from kklcasadi.plant.runs import FAMILIES, fit_families, input_factors

    plant = kc.systems.get("vdp")
    cfg = RolloutConfig(n_traj=14, T=4.0, kinds=FAMILIES, regime="wide", noise_range=(1.0, 1.0), substeps=2)
    wide = replace(cfg, input_scale=scale)
    factors = input_factors(wide, 3)
    if np.ndim(scale):
        assert np.all((factors >= 0.8) & (factors <= 1.6)) and np.unique(factors).size == 14
        assert factors.min() < 1 < factors.max()
    else:
        np.testing.assert_array_equal(factors, np.full(14, 1.5))
    plain, runs = rollouts(plant, cfg, 3), rollouts(plant, wide, 3)
    kinds = np.array([FAMILIES[i % len(FAMILIES)] for i in range(14)])
    loop = np.isin(kinds, ["feedback", "pd"])
    for i in np.flatnonzero(~loop):
        np.testing.assert_allclose(runs.u[i], factors[i] * plain.u[i], rtol=1e-12, atol=1e-15)
    assert np.abs(plain.u[~loop]).max() > 1.0
    amp = np.abs(runs.u).max(axis=(1, 2))
    assert np.all(amp[loop] <= 2.0 * factors[loop] + 1e-12) and np.any(amp[loop] > 2.0)   # the laws' limit
    np.testing.assert_array_equal(rollouts(plant, replace(cfg, input_scale=(1.0, 1.0)), 3).u, plain.u)
    lo, hi = (0.8, 1.6) if np.ndim(scale) else (1.5, 1.5)
    ranges, before = fit_families(wide), fit_families(cfg)
    assert ranges["constant"]["value"] == pytest.approx((-2.0 * hi, 2.0 * hi))
    assert ranges["square"]["amplitude"] == pytest.approx((0.1 * lo, 2.0 * hi))
    assert ranges["feedback"]["limit"] == pytest.approx((2.0 * lo, 2.0 * hi))
    assert ranges["sinusoid"]["omega"] == before["sinusoid"]["omega"] and ranges["pd"]["gain"] == before["pd"]["gain"]


@pytest.mark.parametrize("scale", [0.0, -1.0, (2.0, 1.0), (1.0, 2.0, 3.0), float("nan")])
def test_an_input_scale_must_be_a_factor_or_a_range(scale) -> None:
    with pytest.raises(ValueError, match=r"input_scale: expected a factor > 0 or a range 0 < lo <= hi"):
        RolloutConfig(input_scale=scale)
    assert RolloutConfig(input_scale=[1, 2]).input_scale == (1.0, 2.0)        # a card's list
    assert RolloutConfig(input_scale=(2,)).input_scale == 2.0 and RolloutConfig().input_scale == 1.0


def test_a_range_of_box_scales_spreads_the_initial_states() -> None:
    plant = kc.systems.get("duffing")
    one = rollouts(plant, RolloutConfig(n_traj=40, T=0.1, kinds=("zero",)), 3, measurement_std=0.0, process_std=0.0)
    wide = rollouts(plant, RolloutConfig(n_traj=40, T=0.1, kinds=("zero",), box_scale=(1.0, 3.0)), 3,
                    measurement_std=0.0, process_std=0.0)
    assert np.abs(one.x[:, 0]).max() <= 1.0 < np.abs(wide.x[:, 0]).max() <= 3.0
    ratio = wide.x[:, 0] / one.x[:, 0]                    # the same hypercube, each run scaled by its factor
    np.testing.assert_allclose(ratio[:, 0], ratio[:, 1], rtol=1e-9)
    assert 1.0 <= ratio.min() and ratio.max() <= 3.0
    with pytest.raises(ValueError, match="box_scale"):
        RolloutConfig(box_scale=(2.0, 1.0))
    share = rollouts(plant, RolloutConfig(n_traj=400, T=0.1, kinds=("zero",), box_scale=(2.0, 3.0), box_share=0.25), 3,
                     measurement_std=0.0, process_std=0.0)
    base = rollouts(plant, RolloutConfig(n_traj=400, T=0.1, kinds=("zero",)), 3, measurement_std=0.0, process_std=0.0)
    factor = share.x[:, 0] / base.x[:, 0]                 # 1 (the box itself) or one factor in [2, 3] per run
    spread = factor[:, 0] != 1.0
    assert 0.18 < spread.mean() < 0.32                    # a quarter of 400 runs, within 3 binomial stds
    np.testing.assert_array_equal(factor[~spread], 1.0)
    np.testing.assert_allclose(factor[spread, 0], factor[spread, 1], rtol=1e-9)
    assert 2.0 <= factor[spread].min() and factor[spread].max() <= 3.0
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="box_share"):
            RolloutConfig(box_share=bad)


@pytest.mark.parametrize("xdot, y, sign", [
    (lambda x, u: [x[1], -x[0] - x[0] ** 3 + u], lambda x: x[0], 1.0),     # relative degree 2: H F G
    (lambda x, u: [x[1], -x[0] - 2.0 * u], lambda x: x[0], -1.0),
    (lambda x, u: [-x[0] - 0.5 * u, x[0]], lambda x: x[0], -1.0),          # relative degree 1: H G
    (lambda x, u: [-x[0], -x[1]], lambda x: x[0], 1.0),                    # u acts nowhere: +1
])
def test_loop_signs_are_the_first_nonzero_markov_parameter(xdot, y, sign) -> None:
    from kklcasadi.plant.runs import loop_signs

    x, u = ca.SX.sym("x", 2), ca.SX.sym("u")
    plant = kc.System("p", x, u, xdot(x, u), y(x), x0_box=[[-1.0, 1.0], [-1.0, 1.0]])
    assert loop_signs(plant).tolist() == [sign]


@pytest.mark.parametrize("lag", [0.0, 0.2])
def test_pd_law_is_derivative_feedback_on_the_lagged_noisy_output(lag) -> None:
    """The pd family's closed loop: u_k recomputed from the recorded noisy y_k with an independent lag
    filter (yf_0 = y_0) and difference quotient; the derivative action damps Van der Pol's limit cycle
    onto the set point's equilibrium (x1 = g r / (1 + g)), which the proportional law alone does not."""
    from kklcasadi.plant.runs import _closed_loop, _Feedback

    plant = kc.systems.get("vdp")
    dt, n, g, gd, r = 0.05, 800, 2.0, 3.0, 1.0
    t = np.arange(n) * dt
    law = _Feedback(np.array([g]), np.array([0]), np.array([1.0]), 2.0, np.array([0.0]), np.array([[r]]),
                    np.array([gd]), lag)
    proportional = _Feedback(np.array([g]), np.array([0]), np.array([1.0]), 2.0, np.array([0.0]), np.array([[r]]))
    v = np.random.default_rng(0).normal(0.0, 0.05, (2, n, 1))
    x0 = np.array([[1.5, 0.0], [1.5, 0.0]])
    noisy = _closed_loop(plant, x0, [law, proportional], t, np.zeros(2), [1, 2], v, "rk", 4)
    y, u = noisy.y[0, :, 0], noisy.u[0, :, 0]
    a = 1.0 - np.exp(-dt / lag) if lag > 0 else 1.0
    yf = np.empty(n)
    yf[0] = y[0]
    for k in range(1, n):
        yf[k] = yf[k - 1] + a * (y[k] - yf[k - 1])
    rate = np.concatenate([[0.0], np.diff(yf) / dt])
    np.testing.assert_allclose(u, np.clip(g * (r - y) - gd * rate, -2.0, 2.0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(noisy.u[1, :, 0], np.clip(g * (r - noisy.y[1, :, 0]), -2.0, 2.0), rtol=0, atol=1e-12)
    clean = _closed_loop(plant, x0, [law, proportional], t, np.zeros(2), [1, 2], np.zeros((2, n, 1)), "rk", 4)
    tail = clean.x[:, n // 2:, 0]
    assert abs(tail[0].mean() - g * r / (1 + g)) < 1e-3 and np.ptp(tail[0]) < 1e-3
    assert np.ptp(tail[1]) > 1.0                                       # the limit cycle survives the P law
