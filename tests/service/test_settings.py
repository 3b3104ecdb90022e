"""Settings from a TOML file, the environment and the command line, in rising priority."""
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from service.settings import load_settings


def test_file_then_environment_then_overrides(tmp_path, monkeypatch):
    config = tmp_path / "flyscan.toml"
    config.write_text('port = 9001\nzmq = "tcp://127.0.0.1:6001"\nworkers = 3\n'
                      'data = "/srv/flyscan"\n')
    monkeypatch.setenv("FLYSCAN_WORKERS", "4")
    monkeypatch.setenv("FLYSCAN_TOKEN", "secret")
    settings = load_settings(config, port=9100, host=None)
    assert settings.port == 9100  # the command line wins
    assert settings.workers == 4  # the environment beats the file
    assert settings.zmq == "tcp://127.0.0.1:6001" and settings.data == Path("/srv/flyscan")
    assert settings.host == "127.0.0.1"  # loopback unless told otherwise
    assert settings.token.get_secret_value() == "secret"
    assert "secret" not in repr(settings)


def test_bad_settings_name_the_field(tmp_path, monkeypatch):
    monkeypatch.delenv("FLYSCAN_TOKEN", raising=False)
    config = tmp_path / "flyscan.toml"
    config.write_text("workers = 0\n")
    with pytest.raises(ValidationError, match="workers"):
        load_settings(config)
    config.write_text("wrokers = 2\n")
    with pytest.raises(ValidationError, match="wrokers"):
        load_settings(config)
    with pytest.raises(ValidationError, match="zmq"):
        load_settings(None, zmq="localhost:5556")
    with pytest.raises(FileNotFoundError):
        load_settings(tmp_path / "missing.toml")
    monkeypatch.setenv("FLYSCAN_TOKEN", "")
    assert load_settings(None).token is None  # an empty token is no token


def test_the_simulated_cell_can_be_a_realistic_one(monkeypatch):
    """sim_perturb_seed and sim_effects build the service's simulated cell as ``flyscan scan
    --perturb-seed --effects`` does: its default calibration is that cell's truth, lens and
    all; an unknown effect is named."""
    from flyscan.simdevices import load_sim_settings, simulated_devices
    from simulator.cell import cell_with_effects

    sim = load_sim_settings(None, sim=True, sim_perturb_seed=3, sim_effects="lens,led")
    camera, robot, driver, calibration = simulated_devices(sim)
    try:
        truth = cell_with_effects(3, "lens,led").calibration
        assert calibration.camera.distorted
        assert calibration.camera.distortion == truth.camera.distortion
        np.testing.assert_allclose(calibration.marker_offset_t, truth.marker_offset_t)
    finally:
        camera.close()
    # the settings check the form; the simulated cell, which knows its effects, the names
    with pytest.raises(ValidationError, match="sim_effects"):
        load_sim_settings(None, sim_effects="lens,,fog!")
    with pytest.raises(ValueError, match="fog"):
        simulated_devices(load_sim_settings(None, sim=True, sim_effects="lens,fog"))


def test_the_act_tolerance_reaches_the_pose_and_must_be_one(tmp_path):
    """The cell's placement tolerance (settings) is what the service's poses are judged by;
    none that is not positive is accepted."""
    from flyscan.simdevices import SimSettings, simulated_devices
    from service.daemon import Service

    settings = load_settings(None, data=tmp_path / "data", act_tolerance_mm=0.02,
                             act_tolerance_deg=0.03, robot_rotation_std_deg=0.01)
    devices = simulated_devices(SimSettings(sim=True))
    try:
        service = Service(settings, devices=devices)
        assert service.pose_params.act_tolerance_mm == 0.02
        assert service.pose_params.act_tolerance_deg == 0.03
        assert service.pose_params.robot_rotation_std_deg == 0.01
    finally:
        devices[0].close()
    for field, value in (("act_tolerance_mm", 0.0), ("act_tolerance_deg", -1.0),
                         ("act_tolerance_mm", float("nan")), ("robot_rotation_std_deg", -0.1)):
        with pytest.raises(ValidationError, match=field):
            load_settings(None, **{field: value})


def test_a_taught_place_beyond_the_robot_s_reach_is_no_setting(tmp_path):
    with pytest.raises(ValidationError, match="beyond its reach"):
        load_settings(None, data=tmp_path / "data",
                      taught_place=[0.4, -0.2, 0.1e4, 3.14159, 0.0, 0.0])
    settings = load_settings(None, data=tmp_path / "data", robot_reach_mm=1300.0,
                             taught_place=[0.4, -0.2, 0.1, 3.14159, 0.0, 0.0])
    assert settings.robot_reach_mm == 1300.0


def test_one_settings_file_for_the_service_and_its_simulated_cell(tmp_path, monkeypatch):
    """`flyscan serve --config FILE`: the file's ``sim`` and ``sim_*`` entries are the
    simulated cell's (its own settings, not the service's), the rest the service's; each
    side's environment (``FLYSCAN_SIM_*``) beats the file; a typo is named on either side."""
    from flyscan.serve import load_serve_settings

    config = tmp_path / "flyscan.toml"
    config.write_text('sim = true\nsim_seed = 3\nsim_effects = "lens"\nport = 9002\n')
    monkeypatch.setenv("FLYSCAN_SIM_SEED", "5")
    settings, sim = load_serve_settings(config, host="127.0.0.2")
    assert (settings.port, settings.host) == (9002, "127.0.0.2")
    assert sim.sim and sim.sim_seed == 5 and sim.sim_effects == "lens"
    assert not any(name.startswith("sim") for name in type(settings).model_fields)
    options = sim.options()
    assert (options.seed, options.effects) == (5, "lens")
    config.write_text("sim = true\nsim_sead = 3\n")
    with pytest.raises(ValidationError, match="sim_sead"):
        load_serve_settings(config)
    settings, sim = load_serve_settings(None)
    assert not sim.sim  # a real cell unless told
