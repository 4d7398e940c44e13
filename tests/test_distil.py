"""Distillation of a ``bank`` (kklcasadi.train.distil): a student's decoder is fit to a teacher bank's estimates
along the student's runs, through the teacher's own latent where the two differ."""

from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("torch")

import kklcasadi as kc  # noqa: E402
from kklcasadi.model.files import load_model  # noqa: E402
from kklcasadi.model.operational import operational_data  # noqa: E402
from kklcasadi.model.shipped import resolve  # noqa: E402
from kklcasadi.model.variants import bankdecoder as bd  # noqa: E402
from kklcasadi.plant.runs import RolloutConfig  # noqa: E402
from kklcasadi.train import LoopConfig, default_config, train_observer  # noqa: E402
from kklcasadi.train import bank as bank_training  # noqa: E402
from kklcasadi.train.bank import design_bank, design_copies  # noqa: E402
from kklcasadi.train.decoder import DecoderConfig  # noqa: E402
from kklcasadi.train.distil import teacher_estimates  # noqa: E402

RUNS = RolloutConfig(n_traj=6, T=4.0)


def _config(**changes):
    fields = dict(y_poles=(0.5, 2.0), u_poles=(1.0,), members=1, copies=(), rollouts=RUNS,
                  decoder=DecoderConfig(hidden=(8,), skip=True, loop=LoopConfig(epochs=1, batch_size=64)))
    return replace(default_config("duffing", "bank"), **{**fields, **changes})


@pytest.fixture(scope="module")
def teacher_dir(tmp_path_factory):
    """A two-decoder teacher with one model copy (two RK4 substeps)."""
    config = _config(members=2, copies=(1.0,), copy_substeps=2)
    config = replace(config, monitor=replace(config.monitor, spread_runs=2))
    return train_observer("duffing", "bank", tmp_path_factory.mktemp("teacher") / "bank", config=config, seed=3,
                          progress=False)


def _data(system, config, seed, dt=0.05):
    bank, copies = design_bank(system, config), design_copies(system, config, dt)
    data = operational_data(system, bank, config.rollouts, seed, dt=dt, measurement_std=0.1,
                            process_std=np.full(2, 0.1), time_scale=1.0, copies=copies)
    return bank, copies, data


def _teacher_decode(teacher_dir, z, y, u):
    model = load_model(teacher_dir)
    spec = model.spec.architecture
    return bd.decode(spec.decoder_spec, spec.filter_arrays(model.arrays), z, y, u)


def test_a_student_with_the_teachers_latent_takes_its_estimates_on_its_own_samples(teacher_dir):
    system = kc.systems.get("duffing")
    model = load_model(teacher_dir)
    config = _config(copies=(1.0,), copy_substeps=2)
    bank, copies, data = _data(system, config, seed=8)   # the teacher's design (its gains solved again)

    def never(*_):
        raise AssertionError("the same latent needs no second pass over the runs")

    xhat, record = teacher_estimates(system, teacher_dir, data, bank, copies, dt=0.05, rerun=never, chunk=7)
    assert record["path"] == str(teacher_dir)             # a shipped teacher: its name (below)
    np.testing.assert_array_equal(xhat, _teacher_decode(teacher_dir, data.z, data.y, data.u))
    assert record["latent"].startswith("the student's") and record["members"] == 2
    assert record["weights_sha256"] == model.card["weights_sha256"] and record["copies"]["substeps"] == 2
    np.testing.assert_allclose(record["rmse_to_truth"], np.sqrt(np.mean((xhat - data.x) ** 2, axis=0)), rtol=1e-12)


def test_a_student_without_copies_takes_the_estimates_of_the_teachers_own_latent_on_the_same_runs(teacher_dir):
    system = kc.systems.get("duffing")
    student = _config()
    bank, copies, data = _data(system, student, seed=8)
    assert copies is None and data.z.shape[1] == bank.nz
    rerun = lambda b, c: operational_data(system, b, RUNS, 8, dt=0.05, measurement_std=0.1,  # noqa: E731
                                          process_std=np.full(2, 0.1), time_scale=1.0, copies=c)
    xhat, record = teacher_estimates(system, teacher_dir, data, bank, copies, dt=0.05, rerun=rerun)
    _, _, own = _data(system, _config(copies=(1.0,), copy_substeps=2), seed=8)    # the teacher's latent, same runs
    np.testing.assert_array_equal(own.x, data.x)
    np.testing.assert_allclose(xhat, _teacher_decode(teacher_dir, own.z, own.y, own.u), rtol=0, atol=1e-12)
    assert record["latent"] == "its own, run over the same runs"
    other = lambda b, c: operational_data(system, b, RUNS, 9, dt=0.05, measurement_std=0.1,  # noqa: E731
                                          process_std=np.full(2, 0.1), time_scale=1.0, copies=c)
    with pytest.raises(ValueError, match="rerun: expected the student's runs again"):
        teacher_estimates(system, teacher_dir, data, bank, copies, dt=0.05, rerun=other)


def test_the_student_is_fit_to_the_teachers_estimates_and_its_card_says_so(teacher_dir, tmp_path, monkeypatch):
    seen = {}
    fit_members = bank_training.fit_members

    def spy(bank, data, config, angles, seed, **options):
        seen["data"] = data
        return fit_members(bank, data, config, angles, seed, **options)

    monkeypatch.setattr(bank_training, "fit_members", spy)
    out = train_observer("duffing", "bank", tmp_path / "student", config=_config(teacher=str(teacher_dir)), seed=8,
                         progress=False)
    system = kc.systems.get("duffing")
    bank, _, truth = _data(system, _config(), seed=8)
    _, _, own = _data(system, _config(copies=(1.0,), copy_substeps=2), seed=8)
    np.testing.assert_allclose(seen["data"].x, _teacher_decode(teacher_dir, own.z, own.y, own.u), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(seen["data"].z, truth.z)
    model = load_model(out)
    teacher = model.card["training"]["teacher"]
    assert teacher["path"] == str(teacher_dir) and teacher["decoder"] == [8, 8, 2]  # z: 4 filters, 2 copy states
    assert model.card["training"]["config"]["teacher"] == str(teacher_dir)
    assert "members" not in model.card["architecture"]["bank"] and "copies" not in model.card["architecture"]["bank"]
    # the domain is the true states' range, not the teacher's estimates'
    assert model.spec.domain.x_lo[0] == pytest.approx(truth.x[:, 0].min())


@pytest.mark.parametrize("teacher, message", [("duffing/autonomous", "a bank model directory"),
                                              ("vdp/bank", "a bank model of 'duffing' at dt = 0.05")])
def test_a_teacher_must_be_a_bank_of_the_same_plant(teacher, message, tmp_path):
    system = kc.systems.get("duffing")
    bank, copies, data = _data(system, _config(), seed=1)
    with pytest.raises(ValueError, match=f"teacher: expected {message}"):
        teacher_estimates(system, resolve(teacher), data, bank, copies, dt=0.05, rerun=None)
    with pytest.raises(TypeError, match="teacher"):
        _config(teacher=3)


def test_a_shipped_teacher_is_recorded_by_name():
    system = kc.systems.get("duffing")
    config = _config(y_poles=(0.2, 0.4, 0.8, 1.5, 3.0, 6.0, 12.0, 25.0), u_poles=(0.1, 0.3, 1.0, 3.0, 10.0),
                     copies=(1.0, 100.0, 1e4), rollouts=RolloutConfig(n_traj=2, T=2.0))
    bank, copies, data = _data(system, config, seed=1)
    xhat, record = teacher_estimates(system, "duffing/bank", data, bank, copies, dt=0.05, rerun=None)
    assert record["path"] == "duffing/bank" and record["latent"].startswith("the student's")
    np.testing.assert_array_equal(xhat, _teacher_decode(resolve("duffing/bank"), data.z, data.y, data.u))
