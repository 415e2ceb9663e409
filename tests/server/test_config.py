"""One set of keys across flags, EGOPOSEVR_* variables and a TOML file; flags > environment > file."""

from __future__ import annotations

import pytest

from egoposevr.server.config import ConfigError, ServerConfig, load_config


def test_precedence_flags_then_environment_then_file(tmp_path, monkeypatch):
    config_file = tmp_path / "server.toml"
    config_file.write_text('port = 9001\nmax_sessions = 3\npose_queue = 7\norigins = ["http://a"]\n')
    monkeypatch.setenv("EGOPOSEVR_MAX_SESSIONS", "5")
    monkeypatch.setenv("EGOPOSEVR_TOKEN", "s3cret")
    config = load_config({"port": 1234, "workers": None}, config_file)
    assert (config.port, config.max_sessions, config.pose_queue) == (1234, 5, 7)
    assert config.origins == ("http://a",) and config.token.get_secret_value() == "s3cret"
    assert "s3cret" not in repr(config)  # secrets stay out of logs


def test_the_config_file_may_come_from_the_environment(tmp_path, monkeypatch):
    config_file = tmp_path / "server.toml"
    config_file.write_text("rate_limit_hz = 120.0\n")
    monkeypatch.setenv("EGOPOSEVR_CONFIG", str(config_file))
    monkeypatch.setenv("EGOPOSEVR_ORIGINS", "http://x, http://y")
    config = load_config()
    assert config.rate_limit_hz == 120.0 and config.origins == ("http://x", "http://y")


@pytest.mark.parametrize(
    ("flags", "file_text", "message"),
    [
        ({"max_sessions": 0}, None, "max_sessions"),
        ({"port": 70000}, None, "port"),
        ({}, "bogus = 1\n", "bogus"),
        ({}, "port = \n", "not valid TOML"),
        ({"log_level": "loud"}, None, "log_level"),
    ],
)
def test_bad_values_fail_with_the_key_named(tmp_path, flags, file_text, message):
    path = None
    if file_text is not None:
        path = tmp_path / "server.toml"
        path.write_text(file_text)
    with pytest.raises(ConfigError, match=message):
        load_config(flags, path)


def test_a_missing_config_file_is_an_error(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config({}, tmp_path / "nope.toml")


def test_defaults_are_safe_for_a_laptop():
    config = ServerConfig()
    assert config.host == "127.0.0.1" and config.token is None and config.record is None
