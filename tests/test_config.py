"""robot_change.service.config: TOML -> frozen dataclasses; every error names file, key, value,
rule."""

from __future__ import annotations

import dataclasses
import re

import pytest
from conftest import REPO

from robot_change.change.scene import SceneParams
from robot_change.cloud.chain import CloudParams
from robot_change.errors import ConfigError
from robot_change.link.protocol import PARAM_BY_NAME, PARAMS
from robot_change.service.config import (
    EXIT_CONFIG,
    Config,
    StoreConfig,
    WatchConfig,
    config_from_dict,
    load_config,
)

EXAMPLE = REPO / "systemd" / "robot-change.toml"


def write(tmp_path, text: str):
    path = tmp_path / "robot-change.toml"
    path.write_text(text)
    return path


def error_of(tmp_path, text: str) -> str:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert message.startswith(str(path)), message  # every error names the file
    return message


# ---------------------------------------------------------------------------------------------
# the example file and the defaults


def test_the_example_file_is_accepted_and_holds_every_default():
    config = load_config(EXAMPLE)
    assert config == Config.default()
    assert config.path == EXAMPLE


def test_the_example_file_documents_every_key():
    text = EXAMPLE.read_text()
    for section in Config.default().as_dict():
        assert f"[{section}]" in text
        for field in dataclasses.fields(getattr(Config.default(), section)):
            if field.name == "extra":
                continue
            # set (a default), or shown in a comment when it has no default value
            assert re.search(rf"^#? ?{field.name} = ", text, re.M), f"{section}.{field.name}"


def test_an_empty_file_gives_the_defaults(tmp_path):
    assert load_config(write(tmp_path, "")) == Config.default()


def test_the_protocol_parameters_have_the_same_names_ranges_and_defaults():
    config = Config.default()
    assert config.parameters() == {p.name: p.default for p in PARAMS}
    for p in PARAMS:
        section = next(s for s, table in config.as_dict().items() if p.name in table)
        if p.unit == "bool":
            continue
        for good in (p.minimum, p.maximum):
            config_from_dict({section: {p.name: good}} if p.name not in ("watch_m", "watch_n")
                             else {section: {"watch_m": good, "watch_n": good}})
        for bad in (p.minimum - 1, p.maximum + 1):
            with pytest.raises(ConfigError, match=rf"{section}\.{p.name} = {bad}: must be a "
                               rf"whole number in {p.minimum}\.\.{p.maximum}"):
                config_from_dict({section: {p.name: bad}})


def test_sections_map_onto_cloud_and_scene_params():
    config = config_from_dict({"cloud": {"leaf_m": 0.03, "max_depth_mm": 6000,
                                         "plane_up": [0, -1, 0], "plane_max_tilt_deg": 15},
                               "mixture": {"criterion": "BIC", "max_components": 8},
                               "camera": {"min_valid_fraction": 0.6}})
    params = config.scene_params()
    assert isinstance(params, SceneParams)
    assert params.cloud == CloudParams(leaf_m=0.03, max_depth_m=6.0, plane_up=(0, -1, 0),
                                       plane_max_tilt_deg=15.0)
    assert (params.criterion, params.max_components, params.min_valid_fraction) == ("bic", 8, 0.6)
    assert Config.default().scene_params().cloud == CloudParams()


def test_sections_are_frozen_and_validate_on_construction():
    config = Config.default()
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.watch.watch_m = 4  # type: ignore[misc]
    with pytest.raises(ConfigError, match="watch.watch_m = 6: must be <= watch.watch_n = 5"):
        WatchConfig(watch_m=6)


def test_relative_state_dir_is_taken_from_the_config_folder(tmp_path):
    config = load_config(write(tmp_path, '[store]\nstate_dir = "state"\n'))
    assert config.store.state_dir == str(tmp_path.resolve() / "state")
    assert config.store.references == tmp_path.resolve() / "state" / "references"
    assert StoreConfig().state_dir == "/var/lib/robot-change"


def test_free_form_change_thresholds_are_kept_and_validated(tmp_path):
    config = load_config(write(tmp_path, "[change]\nemd_threshold = 0.25\nsymmetric = true\n"))
    assert dict(config.change.extra) == {"emd_threshold": 0.25, "symmetric": True}
    with pytest.raises(TypeError):
        config.change.extra["x"] = 1  # type: ignore[index]
    assert "change.emd_threshold = \"high\": a free-form threshold must be a finite number" \
        in error_of(tmp_path, '[change]\nemd_threshold = "high"\n')
    assert "did you mean change.min_region_points?" in error_of(
        tmp_path, "[change]\nmin_region_point = 100\n")
    assert "'watch_m' belongs in [watch]" in error_of(tmp_path, "[change]\nwatch_m = 2\n")
    assert "change.Emd = 1: a threshold name is snake_case" in error_of(
        tmp_path, "[change]\nEmd = 1\n")


# ---------------------------------------------------------------------------------------------
# errors: file, dotted key, value, what is allowed


@pytest.mark.parametrize("text, expected", [
    ("[cloud]\nleaf_m = -1\n", "cloud.leaf_m = -1: must be a number with 0.001 <= leaf_m <= 1.0"),
    ("[cloud]\nremove_plane = 1\n", "cloud.remove_plane = 1: must be true or false"),
    ("[cloud]\noutlier_k = 4.5\n", "cloud.outlier_k = 4.5: must be a whole number in 1..26"),
    ("[cloud]\nmin_depth_mm = 6000\n", "cloud.min_depth_mm = 6000: must be below "
                                       "cloud.max_depth_mm = 5000"),
    ("[cloud]\nplane_up = [0, 1]\n", "cloud.plane_up = [0, 1]: must be a non-zero finite 3-vector"),
    ("[cloud]\nplane_up = [0, -1, 0]\n", "cloud.plane_up = [0.0, -1.0, 0.0]: must come with "
                                         "cloud.plane_max_tilt_deg"),
    ("[camera]\nsource = \"rtsp://x\"\n", "camera.source = \"rtsp://x\": must be a depth URI"),
    ("[camera]\nfuse_frames = 0\n", "camera.fuse_frames = 0: must be a whole number in 1..30 "
                                    "frames"),
    ("[camera]\nread_timeout_s = 0\n", "camera.read_timeout_s = 0: must be a number with "
                                       "0.0 < read_timeout_s <= 30.0 seconds"),
    ("[serial]\nbaud = 115201\n", "serial.baud = 115201: must be one of 9600, 19200"),
    ("[serial]\nport = \"\"\n", "serial.port = \"\": must be a non-empty string"),
    ("[mixture]\ncriterion = \"aicc\"\n", "mixture.criterion = \"aicc\": must be one of 'mdl', "
                                          "'bic', 'aic'"),
    ("[mixture]\nmax_components = 0\n", "mixture.max_components = 0: must be a whole number in "
                                        "1..1000"),
    ("[mixture]\nsearch_points = 10\n", "mixture.search_points = 10: must be a whole number "
                                        "in 100.."),
    ("[watch]\nwatch_m = 4\nwatch_n = 3\n", "watch.watch_m = 4: must be <= watch.watch_n = 3"),
    ("[change]\npause_on_change = 1\n", "change.pause_on_change = 1: must be true or false"),
    ("[service]\nlog_level = \"verbose\"\n", "service.log_level = \"verbose\": must be one of "
                                             "'debug', 'info', 'warning', 'error'"),
    ("[service]\nwatchdog = \"yes\"\n", "service.watchdog = \"yes\": must be true or false"),
    ("[viz]\nkeep_checks = -1\n", "viz.keep_checks = -1: must be a whole number in 0..100000"),
    ("[viz]\nlive = \"on\"\n", "viz.live = \"on\": must be true or false"),
    ("[viz]\nlive_port = 70000\n", "viz.live_port = 70000: must be a whole number in 0..65535"),
    ("[viz]\nlive_host = \"robot.local\"\n", "viz.live_host = \"robot.local\": must be an IP "
                                            "address of this machine: \"127.0.0.1\""),
])
def test_a_bad_value_names_key_value_and_what_is_allowed(tmp_path, text, expected):
    assert expected in error_of(tmp_path, text)


@pytest.mark.parametrize("text, expected", [
    ("[camrea]\n", "unknown section [camrea] (known: camera, serial, store, cloud, mixture, "
                   "change, watch, viz, service, fleet); did you mean 'camera'?"),
    ("[viz]\nport = 8765\n", "did you mean 'live_port'? (or 'port' of [serial])"),
    ("[cloud]\nleaf = 0.02\n", "cloud.leaf = 0.02: unknown key (known in [cloud]:"),
    ("[cloud]\nleaf = 0.02\n", "did you mean 'leaf_m'?"),
    ("[serial]\nbaudrate = 9600\n", "did you mean 'baud'?"),
    ("[cloud]\nwatch_n = 5\n", "it belongs in [watch]"),
    ("watch_n = 5\n", "'watch_n' is a key of [watch]"),
    ("camera = 5\n", "camera = 5: must be a table, written [camera]"),
])
def test_unknown_sections_and_keys_are_errors_with_a_suggestion(tmp_path, text, expected):
    assert expected in error_of(tmp_path, text)


def test_invalid_toml_names_line_and_column(tmp_path):
    message = error_of(tmp_path, "[camera]\nfuse_frames = 5\nsource openni2\n")
    assert "invalid TOML" in message and "line 3, column 8" in message


def test_non_utf8_names_line_and_column(tmp_path):
    path = tmp_path / "robot-change.toml"
    path.write_bytes(b"[camera]\nsource = \"caf\xe9\"\n")
    with pytest.raises(ConfigError, match=r"not UTF-8 text \(byte 0xe9 at line 2, column 14\)"):
        load_config(path)


def test_missing_and_unreadable_files(tmp_path):
    with pytest.raises(ConfigError, match="no such configuration file; copy the example"):
        load_config(tmp_path / "absent.toml")
    with pytest.raises(ConfigError, match="is a folder"):
        load_config(tmp_path)
    path = write(tmp_path, "")
    with pytest.raises(ConfigError, match=r"cannot read the configuration file \(Not a "
                       r"directory\); check its permissions"):
        load_config(path / "robot-change.toml")  # an OSError other than "not found"


def test_exit_status_for_config_errors_is_ex_config():
    assert EXIT_CONFIG == 78


def test_each_key_belongs_to_one_section():
    names = [name for table in Config.default().as_dict().values() for name in table]
    assert len(names) == len(set(names))


def test_the_library_and_the_daemon_run_one_set_of_defaults():
    """What `detect` (the library's ChangeParams) and the robot (configuration + wire
    parameters) decide with, when nobody overrides anything, is the same."""
    from robot_change.change.params import ChangeParams
    from robot_change.service.params import change_params

    config = Config()
    assert change_params(config, config.parameters()) == ChangeParams()
    assert PARAM_BY_NAME["min_region_points"].default == ChangeParams().min_region_points
    assert PARAM_BY_NAME["min_region_extent_mm"].default == round(
        ChangeParams().min_region_extent_m * 1000)


def test_unknown_change_keys_are_refused_with_a_hint(tmp_path):
    from robot_change.service.params import check_config

    path = tmp_path / "c.toml"
    path.write_text("[change]\nfree_space_sigma = 3.5\n")
    config = load_config(path)
    with pytest.raises(ConfigError, match="did you mean change.free_space_sigmas"):
        check_config(config)


def test_the_camera_profile_is_a_built_in_or_a_readable_file(tmp_path):
    from robot_change.noise.profile import builtin_profile

    assert Config.default().camera.noise_profile() == builtin_profile("kinect_v1")
    path = tmp_path / "robot-change.toml"
    path.write_text('[camera]\nprofile = "realsense_d435"\n')
    assert load_config(path).camera.noise_profile().name == "realsense_d435"
    path.write_text('[camera]\nprofile = "kinect_v3"\n')
    with pytest.raises(ConfigError, match="camera.profile.*kinect_v1"):
        load_config(path)
    measured = builtin_profile("xtion").raised_by(((2.0, 0.05, 900),), "test", tolerance=1.0)
    measured.save(tmp_path / "camera.json")
    path.write_text('[camera]\nprofile_file = "camera.json"\n')  # beside the file
    assert load_config(path).camera.noise_profile() == measured
    (tmp_path / "broken.json").write_text("{")
    for name in ("broken.json", "missing.json"):
        path.write_text(f'[camera]\nprofile_file = "{name}"\n')
        with pytest.raises(ConfigError, match=f"camera.profile_file.*{name}"):
            load_config(path)


def test_check_config_refuses_what_run_would_fail_on_the_port_and_the_store(tmp_path):
    """What `run` failed on with exit 2 (restarted by systemd until its start limit) while
    check-config and a reload passed it: a serial URL of an unknown scheme or without its
    port, and a store folder the service cannot use; the reports' folder is not one (its files
    are lost, never the service)."""
    from robot_change.service.params import check_config

    state = tmp_path / "state"
    state.mkdir()
    ok = f"[store]\nstate_dir = '{state}'\n"
    check_config(load_config(write(tmp_path, ok + "[serial]\nport = 'socket://127.0.0.1:4001'\n")))
    for port, said in (("sockt://127.0.0.1:1", "unknown scheme 'sockt'"),
                       ("socket://127.0.0.1", "needs HOST:PORT"),
                       ("rfc2217://:4001", "needs HOST:PORT")):
        with pytest.raises(ConfigError, match=f"serial.port = '{port}': .*{said}"):
            check_config(load_config(write(tmp_path, ok + f"[serial]\nport = '{port}'\n")))
    (state / "reports").write_text("not a folder")
    check_config(load_config(write(tmp_path, ok)))
    quarantine = state / "references" / "quarantine"
    quarantine.parent.mkdir()
    quarantine.write_text("not a folder")
    with pytest.raises(ConfigError, match=f"{quarantine} is not a folder"):
        check_config(load_config(write(tmp_path, ok)))
    quarantine.unlink()
    quarantine.parent.rmdir()
    quarantine.parent.write_text("not a folder")
    with pytest.raises(ConfigError, match=f"{quarantine.parent} is not a folder"):
        check_config(load_config(write(tmp_path, ok)))


def test_viz_defaults_are_off_live_bound_to_localhost_and_keep_twenty(tmp_path):
    viz = load_config(write(tmp_path, "")).viz
    assert (viz.keep_checks, viz.live, viz.live_host, viz.live_port) == (20, False,
                                                                          "127.0.0.1", 8765)
    viz = load_config(write(tmp_path, "[viz]\nlive = true\nlive_host = \"::1\"\n"
                                      "live_port = 0\nkeep_checks = 0\n")).viz
    assert (viz.keep_checks, viz.live, viz.live_host, viz.live_port) == (0, True, "::1", 0)


def test_a_live_view_without_foxglove_sdk_is_a_config_error(tmp_path, monkeypatch):
    import sys

    from robot_change.service.params import check_config

    config = load_config(write(tmp_path, f"[store]\nstate_dir = '{tmp_path}'\n[viz]\n"
                                         "live = true\n"))
    check_config(config)  # the library is installed here
    monkeypatch.setitem(sys.modules, "foxglove", None)  # as on a machine without the viz extra
    with pytest.raises(ConfigError, match=r"viz.live = true: Foxglove views of a check need "
                       r"foxglove-sdk: install the 'viz' extra .*; or set viz.live = false"):
        check_config(config)
    # files alone do not need it at load time: the daemon skips them with a warning
    check_config(load_config(write(tmp_path, f"[store]\nstate_dir = '{tmp_path}'\n")))


# ---------------------------------------------------------------------------------------------
# [fleet]


@pytest.mark.parametrize("text, expected", [
    ('[fleet]\nbroker = "http://broker"\n', 'fleet.broker = "http://broker": must be a broker '
                                            'URL mqtt://HOST[:PORT]'),
    ('[fleet]\nbroker = "mqtt://user:pw@broker"\n', "without a path or credentials"),
    ('[fleet]\nrobot_id = "r7"\n', 'fleet.robot_id = "r7": needs fleet.broker'),
    ('[fleet]\nbroker = "mqtt://b"\nrobot_id = "a/b"\n', 'fleet.robot_id = "a/b": must be 1..64'),
    ('[fleet]\nbroker = "mqtt://b"\ntopic_prefix = "a/#"\n', "fleet.topic_prefix"),
    ('[fleet]\nbroker = "mqtt://b"\nca_file = "ca.crt"\n', "needs an mqtts:// broker"),
    ('[fleet]\nbroker = "mqtts://b"\ncert_file = "c.crt"\n', "must come with fleet.key_file"),
    ('[fleet]\nbroker = "mqtt://b"\npassword_file = "pw"\n', "needs fleet.username"),
    ('[fleet]\nbroker = "mqtt://b"\nspool_mb = 0\n', "fleet.spool_mb = 0: must be a number"),
    ('[fleet]\nbroker = "mqtt://b"\npassword = "x"\n', "fleet.password = \"x\": unknown key"),
])
def test_a_bad_fleet_section_is_a_config_error(tmp_path, text, expected):
    assert expected in error_of(tmp_path, text)


def test_the_fleet_is_off_by_default_and_its_files_are_taken_from_the_config_folder(tmp_path):
    assert not Config.default().fleet.enabled
    config = load_config(write(tmp_path, '[fleet]\nbroker = "mqtts://broker.lan"\n'
                               'robot_id = "r7"\nca_file = "ca.crt"\nusername = "r7"\n'
                               'password_file = "/etc/robot-change/pw"\n'))
    fleet = config.fleet
    assert fleet.enabled and fleet.ca_file == str(tmp_path.resolve() / "ca.crt")
    settings = fleet.settings()
    assert (settings.host, settings.port, settings.tls) == ("broker.lan", 8883, True)
    assert settings.password_file == "/etc/robot-change/pw"
    shown = config.as_toml()
    assert '[fleet]\nbroker = "mqtts://broker.lan"\nrobot_id = "r7"' in shown
    assert "password =" not in shown
    assert load_config(write(tmp_path, '[fleet]\nbroker = "mqtt://b"\n')).fleet.robot_id


def test_check_config_reads_the_fleets_files_but_never_prints_the_password(tmp_path):
    from robot_change.service.params import load_checked_config

    (tmp_path / "pw").write_text("hunter2\n")
    text = (f'[store]\nstate_dir = "{tmp_path}"\n[fleet]\nbroker = "mqtt://b"\n'
            'username = "r7"\npassword_file = "pw"\n')
    config = load_checked_config(write(tmp_path, text))
    assert "hunter2" not in config.as_toml() and "hunter2" not in repr(config)
    (tmp_path / "pw").unlink()
    with pytest.raises(ConfigError, match=r"fleet.password_file = .*pw': no such file"):
        load_checked_config(write(tmp_path, text))
    (tmp_path / "pw").write_text("\n")
    with pytest.raises(ConfigError, match="must hold the password alone on one line"):
        load_checked_config(write(tmp_path, text))


def test_check_config_refuses_a_ca_file_that_holds_no_certificate(tmp_path):
    """An mqtts:// broker's CA file is loaded as the daemon will (it was only checked to be a
    readable file, and the fleet failed at start)."""
    from robot_change.service.params import load_checked_config

    (tmp_path / "ca.crt").write_text("not a certificate\n")
    text = (f'[store]\nstate_dir = "{tmp_path}"\n[fleet]\nbroker = "mqtts://b"\n'
            'ca_file = "ca.crt"\n')
    with pytest.raises(ConfigError, match=r"cannot use the CA file .*ca.crt.*PEM certificates"):
        load_checked_config(write(tmp_path, text))
