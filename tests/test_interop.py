"""python-control interop: to_iosys gives a discrete-time NonlinearIOSystem whose
input_output_response equals KKLObserver.simulate (torch-free)."""

import control
import numpy as np
import pytest

from kklcasadi.observer.interop import to_iosys
from kklcasadi.observer.kkl import load_observer

DT = 0.05


@pytest.mark.parametrize("method", ["obs", "dyn", "inject"])
def test_input_output_response_equals_simulate(model_dir_factory, method):
    obs = load_observer(model_dir_factory(method, window=4))
    t = np.arange(50) * DT
    y = np.sin(1.1 * t)[:, None]
    u = 0.6 * np.sign(np.sin(2.5 * t + 0.2))[:, None]
    expected = obs.simulate(t, y, u).xhat
    iosys = to_iosys(obs)
    assert isinstance(iosys, control.NonlinearIOSystem) and iosys.dt == DT
    assert iosys.input_labels == ["y[0]", "u[0]"]
    assert iosys.output_labels == ["xhat[0]", "xhat[1]"]
    assert iosys.nstates == obs.nz + obs.window * obs.nu + obs.ny + 1
    response = control.input_output_response(iosys, t, np.vstack([y.T, u.T]))
    np.testing.assert_allclose(response.outputs.T, expected, rtol=0, atol=1e-12)


def test_iosys_with_two_inputs_and_outputs(model_dir_factory, mimo_plant):
    obs = load_observer(model_dir_factory("obs", system=mimo_plant, window=3), system=mimo_plant)
    iosys = to_iosys(obs, name="mimo_observer")
    assert iosys.name == "mimo_observer"
    assert iosys.input_labels == ["y[0]", "y[1]", "u[0]", "u[1]"]
    assert iosys.output_labels == ["xhat[0]", "xhat[1]"]
    t = np.arange(12) * DT
    y = np.column_stack([np.cos(t), np.sin(2 * t)])
    u = np.column_stack([np.sin(3 * t), np.sign(np.cos(t))])
    response = control.input_output_response(iosys, t, np.vstack([y.T, u.T]))
    np.testing.assert_allclose(response.outputs.T, obs.simulate(t, y, u).xhat, rtol=0,
                               atol=1e-12)


def test_bad_arguments(model_dir_factory):
    with pytest.raises(TypeError, match="observer: expected a KKLObserver"):
        to_iosys("models/duffing/obs")
    obs = load_observer(model_dir_factory("autonomous"))
    with pytest.raises(ValueError, match="name: expected a non-empty string"):
        to_iosys(obs, name="")
