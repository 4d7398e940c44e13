"""The rig's noise from a log (kklcasadi.estimators.noise): the measurement std from the high-frequency
residual, the process std per state by the likelihood of the EKF's innovations."""

from types import SimpleNamespace

import casadi as ca
import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi.estimators.noise import forced_states, process_noise, residual_std


def _oscillator():
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    return kc.System("osc", x, u, [x[1], -x[0] - 0.3 * x[1] - 0.2 * x[0] ** 3 + u], x[0], [[-2, 2], [-2, 2]])


@pytest.mark.parametrize("order", [1, 3])
def test_residual_std_is_zero_on_a_polynomial_of_the_fit_degree_at_jittered_times(order):
    t = np.cumsum(np.random.default_rng(0).uniform(0.003, 0.005, 400))
    y = np.column_stack([1.0 + 2.0 * t ** order, -t])
    np.testing.assert_allclose(residual_std(t, y, order=order), 0.0, atol=1e-9)


@pytest.mark.parametrize("std", [1e-3, 0.05])
def test_residual_std_recovers_white_noise_on_a_smooth_signal(std):
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.0031, 0.0049, 20000))                 # the Qube's jitter
    y = np.column_stack([np.sin(2.0 * t), 0.5 * np.cos(5.0 * t)]) + rng.normal(0.0, std, (t.size, 2))
    np.testing.assert_allclose(residual_std(t, y), std, rtol=0.03)


def test_process_and_measurement_std_of_a_simulated_log_are_recovered_within_20_percent():
    plant = _oscillator()
    dt, process, measurement = 0.01, 0.5, 0.02
    logs = [kc.simulate(plant, [1.0 - seed, 0.0], kc.signals.make("sinusoid", amplitude=1.0, omega=0.7), T=40.0,
                        dt=dt, process_std=[0.0, process], measurement_std=measurement, seed=seed, method="rk")
            for seed in range(3)]
    r = np.sqrt(np.mean([residual_std(log.t, log.y) ** 2 for log in logs]))
    assert abs(r / measurement - 1) < 0.2
    fit = process_noise(plant, logs, dt=dt, measurement_std=r)
    assert fit.states == forced_states(plant) == (1,)
    assert fit.process_std[0] == 0.0 and abs(fit.process_std[1] / process - 1) < 0.2
    assert abs(fit.samples - 3 * (logs[0].t.size - 100)) <= 3 and fit.at_bound == ()
    # one forced state: the shared std is the same optimum
    np.testing.assert_allclose(process_noise(plant, logs, dt=dt, measurement_std=r, shared=True).process_std,
                               fit.process_std, rtol=1e-3)
    record = fit.record()
    assert record["states"] == [1] and record["process_std"][1] == fit.process_std[1]


def test_a_log_without_inputs_runs_at_u_zero_and_bad_logs_are_refused_naming_them():
    plant = _oscillator()
    tr = kc.simulate(plant, [1.0, 0.0], kc.signals.make("zero", size=1), T=5.0, dt=0.01, process_std=[0.0, 0.3],
                     measurement_std=0.01, seed=0, method="rk")
    free = SimpleNamespace(t=tr.t, y=tr.y, u=np.zeros((tr.t.size, 0)))
    a = process_noise(plant, [free], dt=0.01, measurement_std=0.01)
    b = process_noise(plant, [tr], dt=0.01, measurement_std=0.01)
    assert a.nll == b.nll
    with pytest.raises(ValueError, match=r"logs\[0\]: expected samples spaced by dt = 0.02"):
        process_noise(plant, [tr], dt=0.02, measurement_std=0.01)
    with pytest.raises(ValueError, match="settle: expected less than the logs' length"):
        process_noise(plant, [tr], dt=0.01, measurement_std=0.01, settle=10.0)
    with pytest.raises(TypeError, match="logs: expected a non-empty sequence"):
        process_noise(plant, [], dt=0.01, measurement_std=0.01)
    with pytest.raises(ValueError, match=r"states: expected a sequence of distinct indices in \[0, 2\)"):
        process_noise(plant, [tr], dt=0.01, measurement_std=0.01, states=(2,))
    with pytest.raises(ValueError, match="window: expected an odd number"):
        residual_std(tr.t, tr.y, window=4)


def _write_log(path, tr):
    columns = [tr.t, tr.y[:, 0], tr.u[:, 0]]
    header = "time,pos,volts"
    np.savetxt(path, np.column_stack(columns), delimiter=",", header=header, comments="")
    return path


def test_rig_envelope_reads_the_logs_ranges_and_noise_and_names_its_files(tmp_path):
    import hashlib

    from kklcasadi.estimators.noise import rig_envelope

    plant = _oscillator()
    dt, process, measurement = 0.01, 0.5, 0.02
    runs = [kc.simulate(plant, [1.0 - seed, 0.0], kc.signals.make("sinusoid", amplitude=1.0 + seed, omega=0.7),
                        T=40.0, dt=dt, process_std=[0.0, process], measurement_std=measurement, seed=seed, method="rk")
            for seed in range(2)]
    paths = [_write_log(tmp_path / f"run{k}.csv", tr) for k, tr in enumerate(runs)]
    env = rig_envelope(plant, paths, dt=dt, time_col="time", y_cols=("pos",), u_cols=("volts",))
    assert abs(env.measurement_std / measurement - 1) < 0.2
    assert env.process_std[0] == 0.0 and abs(env.process_std[1] / process - 1) < 0.2
    y = np.concatenate([tr.y for tr in runs])
    np.testing.assert_allclose(env.y_range, [[y.min(), y.max()]], rtol=1e-12)
    np.testing.assert_allclose(env.u_range, [[-2.0, 2.0]], atol=1e-3)
    assert [len(u) for u in env.inputs] == [len(s) for s in env.states] == [tr.t.size for tr in runs]
    # the states along the logs are the EKF's: close to the true ones after its transient
    err = np.sqrt(np.mean((env.states[0][200:] - runs[0].x[200:]) ** 2, axis=0))
    assert np.all(err < [0.02, 0.1])
    card = env.to_card()
    assert [s["path"] for s in card["sources"]] == [str(p) for p in paths]
    assert card["sources"][1]["sha256"] == hashlib.sha256(paths[1].read_bytes()).hexdigest()
    assert card["noise"]["process_std_from"] == "logs" and card["noise"]["measurement_std_from"] == "logs"
    # levels the user gives win over the estimates, and a log without inputs gives none
    given = rig_envelope(plant, paths[:1], dt=dt, time_col="time", y_cols=("pos",), measurement_std=0.05,
                         process_std=0.3)
    assert given.measurement_std == 0.05 and given.process_std.tolist() == [0.0, 0.3] and given.inputs == ()
    assert given.u_range is None and given.to_card()["noise"]["process_std_from"] == "given"
    with pytest.raises(ValueError, match="y_cols: expected 1 columns"):
        rig_envelope(plant, paths, dt=dt, time_col="time", y_cols=("pos", "volts"))
    with pytest.raises(TypeError, match="paths: expected a non-empty sequence of CSV logs"):
        rig_envelope(plant, str(paths[0]), dt=dt, time_col="time", y_cols=("pos",))
