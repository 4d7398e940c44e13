"""The training runs where the rig lives (issue 45): inputs across the plant's u_box, integrators kept in the
box by a stabilising loop, and the envelope of a rig's logs (like runs from logged states, outputs bounded)."""

from __future__ import annotations

from dataclasses import replace

import casadi as ca
import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi.model.operational import operational_data
from kklcasadi.model.variants import filterbank as fb
from kklcasadi.plant import runs as rn
from kklcasadi.plant.envelope import LIKE_AMPLITUDE_FACTORS, Envelope
from kklcasadi.plant.runs import FAMILIES, RolloutConfig, fit_families, rollouts


def _oscillator(u_box=None):
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    return kc.System("osc", x, u, [x[1], -x[0] - 0.5 * x[1] + u], x[0], [[-2.0, 2.0], [-2.0, 2.0]], u_box=u_box)


def _mass(u_box=((-1.0, 1.0),)):
    """A mass with viscous friction: its position only drifts (and a held input of 1 drives it at twice the
    box's speed)."""
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    return kc.System("mass", x, u, [x[1], -0.5 * x[1] + u], x[0], [[-1.0, 1.0], [-1.0, 1.0]], u_box=u_box)


def _bank():
    return fb.FilterBank.design(1, 1, [0.5, 2.0], [1.0])


def test_every_family_draws_inside_the_u_box_and_covers_it():
    plant = _oscillator(u_box=[[-1.0, 3.0]])
    cfg = RolloutConfig(n_traj=70, T=20.0, kinds=FAMILIES, chunk=35)
    runs = rollouts(plant, cfg, 0, measurement_std=0.01, process_std=0.0)
    assert len(runs) == 70
    u = runs.u[..., 0]
    assert u.min() >= -1.0 - 1e-12 and u.max() <= 3.0 + 1e-12
    counts, _ = np.histogram(u, bins=10, range=(-1.0, 3.0))
    assert np.all(counts > 0) and u.min() < -0.95 and u.max() > 2.95          # all of it, ends included
    kinds = np.array([FAMILIES[i % len(FAMILIES)] for i in range(70)])
    constants = u[kinds == "constant", 0]                                     # uniform over the box
    assert constants.min() < 0.0 and constants.max() > 2.0
    families = fit_families(cfg, 1.0, plant)
    assert families["constant"]["value"] == (-1.0, 3.0) and families["sinusoid"]["amplitude"] == (0.1, 2.0)
    # without a u_box: the benchmark's ranges, and the source says to declare one
    free = rollouts(_oscillator(), cfg, 0, measurement_std=0.01, process_std=0.0)
    assert np.abs(free.u).max() <= 2.0 + 1e-12
    box, source = rn.input_range(_oscillator())
    assert box is None and "u_box" in source and "|u| <= 2" in source


def test_an_integrator_plant_runs_in_its_box_under_the_stabilising_loop():
    from kklcasadi.train.bank import BankConfig

    plant = _mass()
    assert rn.drifting_states(plant) == (0,) and rn.drifting_states(_oscillator()) == ()
    new = replace(BankConfig.for_system("mass").rollouts, n_traj=36, T=30.0, chunk=36)
    plan = rn.resolved(plant, new)
    assert plan.stabilise is True and plan.escape_scale == rn.ENVELOPE_ESCAPE and plan.fit_after == 0.5
    legacy = rn.resolved(_mass(u_box=None), new)                              # no envelope declared
    assert legacy.escape_scale == rn.LEGACY_ESCAPE and legacy.fit_after == 0.0
    share = {}
    rate = kc.plant.design.time_scales(plant)[0]
    n = rn.time_grid(rn._horizon(new.T, rate, 0.05), 0.05).size
    full = new.n_traj * int(rn._keep(n, 0.05, new, rate).sum())             # the samples of runs never cut
    for stabilise in (True, False):
        data = operational_data(plant, _bank(), replace(new, stabilise=stabilise), 0, dt=0.05, measurement_std=0.01,
                                process_std=0.0)
        assert np.all(np.abs(data.x) <= 1.25 + 1e-12)                          # cut where they leave the box
        share[stabilise] = len(data) / full
        assert data.record["stabilised"] is stabilise and data.record["escape_scale"] == 1.25
        assert sum(k["cut"] for k in data.record["kinds"].values()) == data.record["cut"]
        if stabilise:
            counts, _ = np.histogram(data.x[:, 0], bins=8, range=(-1.0, 1.0))
            assert np.all(counts > 0.03 * len(data))                           # it covers the box
    assert share[True] > 0.8 and share[False] < 0.7 * share[True]          # 0.87 and 0.52 (seed 0)


def _envelope(plant, seed=0):
    """An envelope from a simulated log of ``plant`` under random steps (states and inputs as logged)."""
    u = kc.signals.make("random", amplitude=1.5, hold=0.7, seed=seed, horizon=40.0)
    log = kc.simulate(plant, [0.5, 0.0], u, T=40.0, dt=0.05, measurement_std=0.01, seed=seed, method="rk")
    return Envelope(0.05, (log.u,), (log.x,), np.array([[log.y.min(), log.y.max()]]),
                    np.array([[log.u.min(), log.u.max()]]), 0.01, np.array([0.0, 0.1]),
                    ({"path": "simulated", "sha256": "-", "rows": log.t.size},)), log


def test_a_state_nothing_reads_neither_keeps_a_like_run_from_starting_nor_cuts_it():
    """An arm angle that neither xdot nor y reads (x0, an integrator of x2), logged far outside its box in the
    first half of the log (the EKF's estimate of such a state drifts): like runs still start there, and are not
    cut when it stays out (before, every start came from the second half); the states it reads still bound them."""
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 1)
    arm = kc.System("arm", x, u, [x[2], x[2], -ca.sin(x[1]) - 0.3 * x[2] + u], x[1],
                    [[-1.0, 1.0], [-1.5, 1.5], [-2.0, 2.0]], u_box=[[-1.0, 1.0]])
    u_log = kc.signals.make("random", amplitude=0.5, hold=0.7, seed=0, horizon=40.0)
    log = kc.simulate(arm, [0.0, 0.5, 0.0], u_log, T=40.0, dt=0.05, measurement_std=0.01, seed=0, method="rk")
    states = log.x.copy()
    states[:400, 0] += 10.0
    envelope = Envelope(0.05, (log.u,), (states,), np.array([[log.y.min(), log.y.max()]]),
                        np.array([[log.u.min(), log.u.max()]]), 0.01, np.array([0.0, 0.0, 0.1]),
                        ({"path": "simulated", "sha256": "-", "rows": log.t.size},))
    cfg = RolloutConfig(n_traj=16, T=4.0, kinds=("zero",), envelope=envelope, like_share=1.0, escape_scale=1.25)
    runs = rollouts(arm, cfg, 1, dt=0.05, measurement_std=0.0, process_std=0.0)
    assert len(runs) == 16 and np.all(np.isfinite(runs.x)) and runs.x.shape[1] == 80
    far = np.abs(runs.x[:, :, 0]).min(axis=1) > 5.0                       # never inside its box, kept whole
    assert 3 <= far.sum() <= 13
    for x0 in runs.x[:, 0]:
        assert np.any(np.all(states == x0, axis=1))                          # a state the log holds
    read = kc.systems.get("duffing")                                         # every state read: the box as before
    xs = np.array([[0.0, 0.0], [3.0, 0.0], [0.0, -3.0]])
    np.testing.assert_array_equal(rn._in_read_box(read, xs), rn.inside_box(xs, read.x0_box))


def test_like_runs_replay_rescaled_log_segments_from_the_logged_states():
    plant = _oscillator()
    envelope, log = _envelope(plant)
    cfg = RolloutConfig(n_traj=12, T=10.0, kinds=("zero",), envelope=replace(envelope, y_range=np.array([[-9, 9]])),
                        like_share=1.0, escape_scale=100.0)
    runs = rollouts(plant, cfg, 1, dt=0.05, measurement_std=0.0, process_std=0.0)
    assert len(runs) == 12
    for x, u in zip(runs.x, runs.u[..., 0]):
        start = np.flatnonzero(np.all(log.x == x[0], axis=1))
        assert start.size == 1                                                   # a state the rig was in
        scale = u[0] / log.u[start[0], 0]
        assert LIKE_AMPLITUDE_FACTORS[0] - 1e-12 <= scale <= LIKE_AMPLITUDE_FACTORS[1] + 1e-12
        np.testing.assert_allclose(np.isin(np.round(u / scale, 9), np.round(log.u[:, 0], 9)), True)
    families = fit_families(cfg, 1.0, plant)
    assert set(families) == {"zero", "like"}
    # the families' input range comes from the logs (widened) where the plant declares no u_box
    box, source = rn.input_range(plant, envelope)
    lo, hi = envelope.u_range[0]
    np.testing.assert_allclose(box[0], [lo - 0.25 * (hi - lo) / 2, hi + 0.25 * (hi - lo) / 2])
    assert "logged inputs" in source


def test_the_runs_start_where_the_rig_was_and_its_output_range_bounds_them():
    plant = _oscillator()
    envelope, log = _envelope(plant)
    narrow = replace(envelope, y_range=np.array([[-0.3, 0.3]]))
    cfg = RolloutConfig(n_traj=30, T=10.0, kinds=("sinusoid",), envelope=narrow, like_share=0.0, escape_scale=100.0)
    starts = rn._initial_states(plant, cfg, 0)
    assert all(np.any(np.all(log.x == x, axis=1)) for x in starts)              # states along the log
    data = operational_data(plant, _bank(), cfg, 0, dt=0.05, measurement_std=0.0, process_std=0.0)
    assert 0 < data.record["cut"] <= 30
    assert np.all(np.abs(data.y) <= 0.36 + 1e-12)                                # the range widened by 0.06
    # an angle output turns freely: its logged range bounds nothing
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    pendulum = kc.System("pend", x, u, [x[1], -ca.sin(x[0]) - 0.5 * x[1] + u], x[0], [[-2.0, 2.0], [-2.0, 2.0]],
                         angle_states=(0,), angle_outputs=(0,))
    turning = operational_data(pendulum, _bank(), cfg, 0, dt=0.05, measurement_std=0.0, process_std=0.0)
    assert turning.record["cut"] == 0 and np.abs(turning.y).max() > 0.36
    with pytest.raises(TypeError, match="envelope: expected a kklcasadi.plant.envelope.Envelope"):
        RolloutConfig(envelope={"y_range": [[0, 1]]})


def _plant_file(tmp_path, u_box="None"):
    path = tmp_path / "osc_plant.py"
    path.write_text("import casadi as ca\nimport kklcasadi as kc\n\n\ndef make_plant():\n"
                    "    x, u = ca.SX.sym('x', 2), ca.SX.sym('u', 1)\n"
                    "    return kc.System('osc', x, u, [x[1], -x[0] - 0.5 * x[1] + u], x[0],\n"
                    f"                     [[-2.0, 2.0], [-2.0, 2.0]], u_box={u_box})\n")
    return path


def _log_file(tmp_path):
    plant = _oscillator()
    tr = kc.simulate(plant, [0.5, 0.0], kc.signals.make("random", amplitude=1.5, hold=0.7, seed=3, horizon=30.0),
                     T=30.0, dt=0.05, process_std=[0.0, 0.3], measurement_std=0.01, seed=3, method="rk")
    path = tmp_path / "rig.csv"
    np.savetxt(path, np.column_stack([tr.t, tr.u[:, 0], tr.y[:, 0]]), delimiter=",", header="t,volts,pos",
               comments="")
    return path


@pytest.mark.parametrize("flags, message", [
    (["--y-cols", "pos"], "--y-cols: names the columns of the logs of --like, received no --like LOG.csv"),
    (["--like", "{log}"], "--y-cols: expected the logs' columns of the 1 output(s) of 'osc'"),
    (["--like", "{log}", "--y-cols", "pos"], "--u-cols: expected the logs' column(s) of the 1 input(s) of 'osc', "
     "received none; pass --u-zero"),
    (["--like", "{log}", "--y-cols", "pos,volts", "--u-zero"], "--y-cols: expected 1 columns"),
    (["--like", "{log}", "--y-cols", "pos", "--u-cols", "volts", "--time-col", "time"],
     "--time-col: expected a column of "),
    (["--like", "{log}", "--time-col", "t", "--y-cols", "pos", "--u-zero", "--method", "autonomous"],
     "--like: only --method bank takes it, received --method autonomous"),
])
def test_train_like_refuses_what_it_cannot_read_naming_the_flag(tmp_path, capsys, flags, message):
    pytest.importorskip("torch")
    from kklcasadi.cli import main

    log = _log_file(tmp_path)
    argv = ["train", "--plant", f"{_plant_file(tmp_path)}:make_plant", "--out", str(tmp_path / "m"),
            *[f.format(log=log) for f in flags]]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1


def test_train_like_takes_the_rigs_envelope_into_the_runs_and_the_card(tmp_path, capsys, monkeypatch):
    pytest.importorskip("torch")
    import hashlib

    import kklcasadi.train as training
    from kklcasadi.cli import main
    from kklcasadi.model.files import load_model

    def tiny(system, method, **kw):          # the new-plant bank recipe on a budget a test can afford
        config = training.default_config.__wrapped__(system, method, **kw)
        return replace(config, rollouts=replace(config.rollouts, n_traj=16, T=4.0, chunk=16),
                       decoder=replace(config.decoder, hidden=(16,), loop=replace(config.decoder.loop, batch_size=64)))

    tiny.__wrapped__ = training.default_config
    monkeypatch.setattr(training, "default_config", tiny)
    log, out = _log_file(tmp_path), tmp_path / "m"
    assert main(["train", "--plant", f"{_plant_file(tmp_path)}:make_plant", "--like", str(log), "--time-col", "t",
                 "--y-cols", "pos", "--u-cols", "volts", "--epochs", "1", "--quiet", "--out", str(out)]) == 0
    card = load_model(out).card
    envelope = card["training"]["rollouts"]["envelope"]
    assert envelope["sources"][0]["sha256"] == hashlib.sha256(log.read_bytes()).hexdigest()
    assert envelope["noise"]["process_std_from"] == "logs" and envelope["process_std"][0] == 0.0
    assert card["training"]["measurement_std"] == envelope["measurement_std"] == card["noise"]["measurement_std"]
    assert abs(envelope["process_std"][1] / 0.3 - 1) < 0.5                      # 30 s of log: roughly
    assert card["training"]["input_range"]["source"].startswith("the logged inputs' range")
    assert card["domain"]["x_lo"] == [-2.0, -2.0] and card["domain"]["x_hi"] == [2.0, 2.0]
    assert "like" in card["fit_families"] and card["training"]["runs"]["kinds"]["like"]["runs"] == 8
    # the plant declares where it lives: its latent holds a copy at the training noise's ratio, per state
    ratio = [(q / envelope["measurement_std"]) ** 2 for q in envelope["process_std"]]
    np.testing.assert_allclose(card["architecture"]["bank"]["copies"]["weights"], [ratio], rtol=1e-12)
    assert card["training"]["noise_copy"].startswith("one copy at the training noise's ratio")
    assert card["training"]["config"]["copy_residual"] is True                  # the decoders correct that copy
    assert card["architecture"]["decoder"]["skip"] is True
    # a flag wins over the estimate
    assert main(["train", "--plant", f"{_plant_file(tmp_path)}:make_plant", "--like", str(log), "--time-col", "t",
                 "--y-cols", "pos", "--u-cols", "volts", "--process-std", "0.7", "--epochs", "1", "--quiet",
                 "--overwrite", "--out", str(out)]) == 0
    card = load_model(out).card
    assert card["noise"]["process_std"] == [0.0, 0.7] and card["training"]["rollouts"]["envelope"]["noise"][
        "process_std_from"] == "given"
    # a plant with inputs and no u_box (and no logs) says so in one line naming u_box
    capsys.readouterr()
    assert main(["train", "--plant", f"{_plant_file(tmp_path)}:make_plant", "--epochs", "1", "--quiet",
                 "--overwrite", "--out", str(out)]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "u_box" in line]
    assert len(lines) == 1 and "declares no u_box" in lines[0]


def test_the_noise_copy_goes_where_the_plant_declares_where_it_lives():
    pytest.importorskip("torch")
    from kklcasadi.train.bank import BankConfig, with_noise_copy

    config = replace(BankConfig.for_system("mass"), measurement_std=0.01, process_std=0.5)
    added, text = with_noise_copy(_mass(), config)
    assert added.copies == ((0.0, 2500.0),) and added.noise_copy is False and "intensities [0.0, 2500.0]" in text
    assert added.decoder.skip and not config.decoder.skip
    assert added.copy_residual and not config.copy_residual and "residual over its estimate" in text
    assert with_noise_copy(_mass(u_box=None), config)[0].copies == ()                 # declares nothing
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    pendulum = kc.System("pend", x, u, [x[1], -ca.sin(x[0]) + u], x[0], [[-3, 3], [-2, 2]], angle_states=(0,),
                         u_box=[[-1, 1]])
    added, what = with_noise_copy(pendulum, config)                   # angle states: a copy, corrected
    assert len(added.copies) == 1 and added.copy_residual and "residual over its estimate" in what
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 1)     # an arm's angle that nothing reads: a copy over the other states
    arm = kc.System("arm", x, u, [x[2], x[2], -ca.sin(x[1]) + u], x[1], [[-3, 3], [-3, 3], [-2, 2]],
                    angle_states=(0, 1), angle_outputs=(0,), u_box=[[-1, 1]])
    added, what = with_noise_copy(arm, config)
    assert len(added.copies) == 1 and added.copy_residual and "over the states its equations read [1, 2]" in what
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)       # not detectable even over the read states: no copy, and why
    blind = kc.System("blind", x, u, [x[1], x[1] + u], x[1] ** 3, [[-1, 1], [-1, 1]], u_box=[[-1, 1]])
    kept, why = with_noise_copy(blind, config)
    assert kept.copies == () and kept.noise_copy is False and "stabilising Kalman-Bucy gain" in why
    assert with_noise_copy(_mass(), replace(config, noise_copy=False))[0].copies == ()
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)      # an angle output of no angle state: a copy, corrected
    wheel = kc.System("wheel", x, u, [x[1], -0.5 * x[1] + u], [x[0], x[1]], [[-3, 3], [-2, 2]], angle_outputs=(0,),
                      u_box=[[-1, 1]])
    read, what = with_noise_copy(wheel, config)
    assert len(read.copies) == 1 and read.copy_residual and "residual over its estimate" in what
    assert with_noise_copy(_mass(u_box=None), replace(config, noise_copy=True))[0].copies == ((0.0, 2500.0),)
    for bad in ({"copies": ((0.0, 0.0),)}, {"copies": (-1.0,)}, {"noise_copy": "yes"}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            replace(config, **bad)


def test_fit_after_leaves_the_latents_first_moments_out_of_the_fit():
    plant = _oscillator()
    cfg = RolloutConfig(n_traj=4, T=6.0, kinds=("sinusoid",), dense_time=1.0, dense_period=0.1, sample_period=0.5)
    late = replace(cfg, fit_after=2.0)
    n = rn.time_grid(6.0, 0.05).size
    full = rn._keep(n, 0.05, cfg)
    np.testing.assert_array_equal(rn._keep(n, 0.05, late), full & (np.arange(n) * 0.05 >= 2.0 - 1e-9))
    data = operational_data(plant, _bank(), late, 0, dt=0.05, measurement_std=0.0, process_std=0.0)
    assert data.t.min() >= 2.0 - 1e-9 and len(data) == 4 * int(full[40:].sum())
    with pytest.raises(ValueError, match="fit_after: expected a time >= 0 and below T"):
        replace(cfg, fit_after=6.0)


@pytest.mark.parametrize("x,scale,angles,expected", [
    ([[0.5, 2.9]], 1.0, (), [True]),                  # box [0, 1] x [1, 3]: inside
    ([[1.1, 2.0]], 1.0, (), [False]),                 # past hi on state 0
    ([[1.1, 2.0]], 1.25, (), [True]),                 # inside the box widened by a quarter about its centre
    ([[-0.14, 2.0]], 1.25, (), [False]),              # centre 0.5, half-width 0.625: below -0.125
    ([[0.5, 3.0 + 2 * np.pi]], 1.0, (1,), [True]),    # an angle state one turn off: the same point
    ([[0.5, 3.0 + 2 * np.pi]], 1.0, (), [False]),     # ... not for a plain state
    ([[np.nan, 2.0], [0.2, np.inf]], 1.0, (), [False, False]),   # not finite: outside
])
def test_inside_box_against_hand_computations(x, scale, angles, expected):
    """``kklcasadi.plant.runs.inside_box``: the per-sample box test training cuts its runs with and the train
    summary scores by."""
    from kklcasadi.plant.runs import inside_box

    box = np.array([[0.0, 1.0], [1.0, 3.0]])
    got = inside_box(np.array(x), box, angles, scale=scale)
    assert got.tolist() == expected


def test_inside_box_refuses_a_box_of_the_wrong_shape():
    from kklcasadi.plant.runs import inside_box

    with pytest.raises(ValueError, match=r"box: expected shape \(nx, 2\) = \(2, 2\).*received shape \(3, 2\)"):
        inside_box(np.zeros((4, 2)), np.zeros((3, 2)))


def _copy_data(measurement_std=0.0):
    """Operational samples of the mass through a small bank and one model copy (its latents last in ``z``)."""
    from kklcasadi.model.variants.copies import ModelCopies

    plant, bank = _mass(), _bank()
    copies = ModelCopies.design(plant, [(0.0, 100.0)])
    cfg = RolloutConfig(n_traj=12, T=8.0, kinds=("sinusoid", "square"), chunk=12, stabilise=True)
    data = operational_data(plant, bank, cfg, 0, dt=0.05, measurement_std=measurement_std, process_std=0.0,
                            copies=copies)
    return plant, bank, copies, data


def test_a_decoder_fitted_over_a_base_evaluates_the_base_plus_its_correction():
    """A base that holds a state exactly (the measured position, without noise) gives it back to rounding, through the
    folded skip path of the arrays (numpy and torch alike), where the network alone misses it by its fitting error;
    the other state is normalised as before; bad bases are refused."""
    torch = pytest.importorskip("torch")
    from kklcasadi.model.variants import bankdecoder as bd
    from kklcasadi.train.config import LoopConfig
    from kklcasadi.train.decoder import DecoderConfig, fit_bank_decoder, torch_decoder

    plant, bank, _, data = _copy_data()
    np.testing.assert_array_equal(data.x[:, 0], data.y[:, 0])                       # y = q, no noise
    n_features = data.z.shape[1] + 2
    base = np.zeros((2, n_features))
    base[0, data.z.shape[1]] = 1.0                                                    # x_0 over the feature y
    config = DecoderConfig(hidden=(16,), skip=True, dtype="float64",
                           loop=LoopConfig(epochs=3, batch_size=64, lr=1e-3, val_fraction=0.1))
    over = fit_bank_decoder(bank, data, config, base=base)
    plain = fit_bank_decoder(bank, data, config)
    assert over.spec == plain.spec and set(over.arrays) == set(plain.arrays)          # the same model format
    xhat = bd.decode(over.spec, over.arrays, data.z, data.y, data.u)
    np.testing.assert_allclose(xhat[:, 0], data.x[:, 0], rtol=0, atol=1e-9)
    assert np.sqrt(np.mean((bd.decode(plain.spec, plain.arrays, data.z, data.y, data.u)[:, 0] - data.x[:, 0]) ** 2)
                   ) > 1e-4
    again = torch_decoder(over.spec, over.arrays)(*(torch.as_tensor(a) for a in (data.z, data.y, data.u)))
    np.testing.assert_allclose(again.detach().numpy(), xhat, rtol=0, atol=1e-12)
    # the state without a base is normalised as before; the one over it by its residual's spread (0 here)
    assert over.arrays["decoder/out_std"][1] == plain.arrays["decoder/out_std"][1]
    np.testing.assert_allclose(over.arrays["decoder/out_std"][1], data.x[:, 1].std(), rtol=1e-10)
    assert over.arrays["decoder/out_std"][0] < 1e-11 < plain.arrays["decoder/out_std"][0]
    with pytest.raises(ValueError, match=r"base: expected a finite matrix of shape \(outputs, features\)"):
        fit_bank_decoder(bank, data, config, base=base[:, :-1])
    with pytest.raises(ValueError, match="base: expected None for a decoder without the linear skip path"):
        fit_bank_decoder(bank, data, replace(config, skip=False), base=base)


def test_copy_base_picks_the_last_copys_latents():
    pytest.importorskip("torch")
    from kklcasadi.model.variants import bankdecoder as bd
    from kklcasadi.train.bank import BankConfig, copy_base

    plant, bank, copies, data = _copy_data(measurement_std=0.01)
    base = copy_base(plant, bank, copies, bd.NO_ANGLES, np.zeros(2))
    features = bd.decoder_features(data.z, data.y, data.u)
    np.testing.assert_array_equal(features @ base.T, data.z[:, -2:])                 # z_i = xhat_i - r_i
    late = data.t >= 3.0                                                             # after the copy's transient
    error = data.z[late, -2:] + copies.reference - data.x[late]
    assert np.all(np.sqrt(np.mean(error ** 2, axis=0)) < 0.1 * data.x.std(axis=0))
    np.testing.assert_array_equal(copy_base(plant, bank, copies, bd.NO_ANGLES, np.array([0.0, 2.0]))[1], 0.0)
    with pytest.raises(ValueError, match="copy_residual: expected False for a decoder without model copies"):
        replace(BankConfig(), copy_residual=True)


@pytest.mark.parametrize("v, offset, expected", [
    # an angle column's residual on the branch about its circular mean (-0.0342 here): 6 - 2 pi, -6 + 2 pi, -0.1
    ([[3.0, 1.0], [-3.0, 2.0], [0.1, 3.0]], [[-3.0, 0.5], [3.0, 0.5], [0.2, 0.5]],
     [[6.0 - 2 * np.pi, 0.5], [-6.0 + 2 * np.pi, 1.5], [-0.1, 2.5]]),
    # about pi: pi - 0.1 and pi + 0.1 (not -pi + 0.1), the second column as it is
    ([[np.pi - 0.1, 0.0], [-np.pi + 0.1, 7.0]], [[0.0, 0.0], [0.0, 0.0]], [[np.pi - 0.1, 0.0], [np.pi + 0.1, 7.0]]),
    # a copy's deviation near pi (its reference angle -pi), the targets near 0: the residual's circular mean is
    # pi - 0.02, its branch pi + 0.01, pi - 0.05, which would write every estimate a turn above its measurement
    # (offset + residual near 2 pi); moved by a turn: -pi + 0.01, -pi - 0.05
    ([[0.02, 1.0], [-0.02, 1.0]], [[np.pi + 0.01, 0.0], [np.pi + 0.03, 0.0]],
     [[-np.pi + 0.01, 1.0], [-np.pi - 0.05, 1.0]]),
])
def test_an_angles_residual_over_a_base_against_hand_computations(v, offset, expected):
    pytest.importorskip("torch")
    from kklcasadi.model.variants import bankdecoder as bd
    from kklcasadi.train.decoder import base_residual

    got = base_residual(np.array(v), np.array(offset), bd.Angles(outputs=(0,), measured=((0, 0),)))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(base_residual(np.array(v), np.array(offset), bd.NO_ANGLES),
                                  np.array(v) - np.array(offset))


def _pendulum(u_box=((-1.0, 1.0),)):
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    return kc.System("pend", x, u, [x[1], -ca.sin(x[0]) - 0.3 * x[1] + u], x[0], [[-2.5, 2.5], [-2.5, 2.5]],
                     angle_states=(0,), angle_outputs=(0,), u_box=u_box)


def test_a_decoder_over_a_base_writes_an_angle_the_base_holds_turns_off():
    """A base that holds a measured angle exactly up to whole turns (a copy's angle one or more turns off the
    target's branch) gives the angle back to rounding modulo 2 pi: its residual, taken on the circle, is one
    constant; the velocity over its copy's latent is fitted as a state is."""
    torch = pytest.importorskip("torch")
    from kklcasadi.model.variants import bankdecoder as bd
    from kklcasadi.model.variants.copies import ModelCopies
    from kklcasadi.train.bank import copy_base
    from kklcasadi.train.config import LoopConfig
    from kklcasadi.train.decoder import DecoderConfig, fit_bank_decoder, torch_decoder

    plant, bank = _pendulum(), _bank()
    copies = ModelCopies.design(plant, [(1.0, 100.0)])
    cfg = RolloutConfig(n_traj=12, T=8.0, kinds=("sinusoid", "square"), chunk=12, stabilise=True)
    data = operational_data(plant, bank, cfg, 0, dt=0.05, measurement_std=0.01, process_std=0.0, copies=copies)
    angles = bd.Angles.of(plant)
    turns = np.random.default_rng(0).integers(-2, 3, len(data))
    z = data.z.copy()
    z[:, -2] = data.x[:, 0] + 2 * np.pi * turns - copies.reference[0]     # the copy's angle: x, some turns off
    data = replace(data, z=z)
    base = copy_base(plant, bank, copies, angles, np.zeros(2))
    features = bd.decoder_features(data.z, data.y, data.u, angles=angles,
                                   gains=bd.latent_gains(bank, data.z.shape[1], 2, angles))
    np.testing.assert_allclose(features @ base.T, np.column_stack([z[:, -2] - data.y[:, 0], z[:, -1]]), atol=1e-12)
    config = DecoderConfig(hidden=(16,), skip=True, dtype="float64",
                           loop=LoopConfig(epochs=3, batch_size=64, lr=1e-3, val_fraction=0.1))
    over = fit_bank_decoder(bank, data, config, angles=angles, base=base)
    xhat = bd.decode(over.spec, over.arrays, data.z, data.y, data.u)
    np.testing.assert_allclose(np.angle(np.exp(1j * (xhat[:, 0] - data.x[:, 0]))), 0.0, atol=1e-9)
    assert over.arrays["decoder/out_std"][0] < 1e-11
    again = torch_decoder(over.spec, over.arrays)(*(torch.as_tensor(a) for a in (data.z, data.y, data.u)))
    np.testing.assert_allclose(again.detach().numpy(), xhat, rtol=0, atol=1e-12)


def test_a_plant_with_angle_states_trains_over_its_noise_copy(tmp_path):
    """A pendulum (an angle state, measured) asked for its noise copy trains with the residual fit; the observer
    (CasADi) equals the decoder in numpy on its own latents (the copy's gains in the features) and holds the
    pendulum measured one turn on."""
    pytest.importorskip("torch")
    from kklcasadi.model.files import load_model
    from kklcasadi.model.variants import bankdecoder as bd
    from kklcasadi.train import train_observer
    from kklcasadi.train.bank import BankConfig

    plant = _pendulum()
    base = BankConfig.for_system("pend")
    config = replace(base, measurement_std=0.01, process_std=0.3, noise_copy=True,
                     rollouts=replace(base.rollouts, n_traj=16, T=6.0),
                     decoder=replace(base.decoder, hidden=(16,), loop=replace(base.decoder.loop, epochs=2)))
    train_observer(plant, "bank", tmp_path / "m", config=config, dt=0.05, seed=0, progress=False, threads=1)
    model = load_model(tmp_path / "m")
    assert model.card["training"]["config"]["copy_residual"] is True and model.card["architecture"]["decoder"]["skip"]
    obs = kc.load_observer(tmp_path / "m", system=plant)
    sim = kc.simulate(plant, [1.0, 0.0], lambda tt: 0.5 * np.sin(tt), T=6.0, dt=0.05, measurement_std=0.01, seed=4)
    t, y = sim.t, sim.y + 2 * np.pi                                           # one turn on: the same pendulum
    run = obs.simulate(t, y, sim.u)
    spec = model.spec.architecture
    arrays = {**model.arrays, **fb.bank_arrays(spec.filter_bank(model.arrays))}
    spec = spec.decoder_spec
    np.testing.assert_allclose(run.xhat, bd.decode(spec, arrays, run.z, y, sim.u), rtol=0, atol=1e-9)
    err = np.angle(np.exp(1j * (run.xhat[t >= 3.0, 0] - sim.x[t >= 3.0, 0])))
    assert np.sqrt(np.mean(err ** 2)) < 0.1
