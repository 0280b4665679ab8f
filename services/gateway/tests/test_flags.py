"""The gateway's command line mirrors its settings: one flag per field of ``GatewaySettings``, made from the field
(name, type, description), so that neither can change without the other; the environment still fills what no flag
gives."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from twohr.errors import TwohrError
from twohr_services.gateway.__main__ import NOT_FLAGS, build_parser, settings_from_args
from twohr_services.gateway.settings import GatewaySettings


def test_every_setting_is_one_flag_whose_help_is_its_description():
    parser = build_parser()
    by_dest = {action.dest: action for action in parser._actions}
    for name, field in GatewaySettings.model_fields.items():
        if name in NOT_FLAGS:
            assert name not in by_dest
            continue
        flag = by_dest[name]
        assert len(flag.option_strings) == 1 and field.description and field.description in flag.help, name
    assert {"--idle-timeout", "--max-request-bytes", "--map-grants", "--foxglove-host"} <= {
        option for action in parser._actions for option in action.option_strings}
    shown = subprocess.run([sys.executable, "-m", "twohr_services.gateway", "--help"], capture_output=True, text=True,
                           timeout=60)
    assert shown.returncode == 0 and "--liveliness-grace" in shown.stdout and "--keep-ended" in shown.stdout


def test_flags_become_settings_and_the_environment_fills_the_rest(monkeypatch):
    monkeypatch.setenv("TWOHR_API_TOKEN", "t" * 20)
    args = build_parser().parse_args([
        "--data-root", "a", "--data-root", "b", "--recordings", "rec", "--idle-timeout", "2.5", "--keep-ended", "7",
        "--max-request-bytes", "4096", "--max-robots", "1.5", "--map-versions", "3", "--foxglove-port", "0",
        "--map-grants", "g.json", "--host", "0.0.0.0"])
    settings = settings_from_args(args)
    assert settings.data_roots == [Path("a"), Path("b")] and settings.recordings == Path("rec")
    assert (settings.idle_timeout, settings.keep_ended, settings.max_request_bytes) == (2.5, 7, 4096)
    assert (settings.max_robots, settings.map_versions, settings.map_grants) == (1.5, 3, Path("g.json"))
    assert settings.foxglove_port is None and settings.foxglove_host == "0.0.0.0"  # 0: off; the live view on --host
    assert settings.api_token == "t" * 20 and settings.stall_timeout == 45.0  # none given: the environment, the field
    defaults = settings_from_args(build_parser().parse_args(["--api-token", "u" * 16, "--foxglove-host", "::1"]))
    assert defaults.api_token == "u" * 16 and defaults.foxglove_port == 8765 and defaults.foxglove_host == "::1"
    assert defaults.data_roots == [Path("data")] and defaults.idle_timeout == 15.0


def test_a_value_the_settings_refuse_is_one_line():
    with pytest.raises(TwohrError, match="idle_timeout"):
        settings_from_args(build_parser().parse_args(["--idle-timeout", "0"]))
    refused = subprocess.run([sys.executable, "-m", "twohr_services.gateway", "--keep-ended", "many"],
                             capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and "--keep-ended: invalid int value: 'many'" in refused.stderr
