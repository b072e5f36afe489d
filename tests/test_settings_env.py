"""Settings from the environment (`ARENA_...`) and keys from a file, as services pass them."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from arena.protocol.errors import ArenaError
from arena.server.config import ServerConfig, load_config
from tests.serve_process import serving

ROOT = Path(__file__).resolve().parent.parent


def test_every_kind_of_setting_comes_from_its_variable() -> None:
    config = load_config(
        None,
        {
            "ARENA_PORT": "9001",
            "ARENA_HOST": "0.0.0.0",
            "ARENA_INSECURE": "yes",
            "ARENA_RECORD": "false",
            "ARENA_HEARTBEAT_TIMEOUT": "12.5",
            "ARENA_ALLOWED_HOSTS": "arm.local, pi.lan,",
            "ARENA_FOXGLOVE_PORT": "8765",
            "ARENA_CERTFILE": "/etc/arena/cert.pem",
        },
    )
    assert (config.port, config.host, config.insecure, config.record) == (
        9001,
        "0.0.0.0",
        True,
        False,
    )
    assert config.heartbeat_timeout == 12.5
    assert config.allowed_hosts == ("arm.local", "pi.lan")
    assert config.foxglove_port == 8765
    assert config.certfile == "/etc/arena/cert.pem"


def test_a_flag_wins_over_the_environment_which_wins_over_the_file(tmp_path: Path) -> None:
    file = tmp_path / "arena.toml"
    file.write_text('port = 7000\nrecordings_dir = "from-file"\nrecord = false\n')
    env = {"ARENA_PORT": "8000", "ARENA_RECORDINGS_DIR": "from-env"}
    assert load_config(str(file), {}).port == 7000
    config = load_config(str(file), env)
    assert (config.port, config.recordings_dir, config.record) == (8000, "from-env", False)
    config = load_config(str(file), env, port=9000)
    assert (config.port, config.recordings_dir) == (9000, "from-env")
    # ARENA_CONFIG names the file when no --config does
    assert load_config(None, {**env, "ARENA_CONFIG": str(file)}).record is False


def test_api_keys_add_up_from_file_environment_key_file_and_flags(tmp_path: Path) -> None:
    (tmp_path / "arena.toml").write_text('api_keys = ["from-toml"]\n')
    (tmp_path / "keys").write_text("# the operators' keys\nfrom-key-file\n\n  second-key  \n")
    config = load_config(
        str(tmp_path / "arena.toml"),
        {"ARENA_API_KEYS": "env-a, env-b", "ARENA_API_KEY_FILE": str(tmp_path / "keys")},
        api_keys=("from-flag",),
    )
    assert config.api_keys == (
        "from-toml",
        "env-a",
        "env-b",
        "from-key-file",
        "second-key",
        "from-flag",
    )


@pytest.mark.parametrize(
    ("variable", "value", "sentence"),
    [
        ("ARENA_PORT", "eighty", "ARENA_PORT='eighty': expected an integer."),
        ("ARENA_RECORD", "maybe", "ARENA_RECORD='maybe': expected true or false."),
        ("ARENA_SHUTDOWN_GRACE", "1s", "ARENA_SHUTDOWN_GRACE='1s': expected a number."),
    ],
)
def test_a_value_that_does_not_parse_is_refused_naming_its_variable(
    variable: str, value: str, sentence: str
) -> None:
    with pytest.raises(ArenaError) as refused:
        load_config(None, {variable: value})
    assert refused.value.message == sentence


def test_an_unknown_arena_variable_is_a_warning_naming_it(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with caplog.at_level(logging.WARNING):
        config = load_config(None, {"ARENA_PROT": "9000", "ARENA_ROBOT_TYPES": "/x", "HOME": "/"})
    assert config == ServerConfig()
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings == ["ARENA_PROT is no Arena setting: ignored (is it misspelt?)"]


@pytest.mark.parametrize("content", ["", "# only a comment\n\n"])
def test_a_key_file_without_keys_or_missing_is_refused(tmp_path: Path, content: str) -> None:
    keys = tmp_path / "keys"
    keys.write_text(content)
    with pytest.raises(ArenaError, match="holds no key"):
        load_config(None, {}, api_key_file=str(keys))
    with pytest.raises(ArenaError, match="Cannot read the API key file"):
        load_config(None, {}, api_key_file=str(tmp_path / "absent"))


def test_serve_refuses_a_bad_variable_in_one_line(tmp_path: Path) -> None:
    # A process of its own: were the variable ignored, it would serve (until the timeout).
    done = subprocess.run(
        [sys.executable, "-m", "arena", "serve", "--port", "0"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT), "ARENA_PORT": "eighty"},
        timeout=60,
    )
    assert done.returncode == 2
    assert done.stderr == "arena serve: ARENA_PORT='eighty': expected an integer.\n"


def test_a_served_process_takes_its_settings_from_the_environment_and_keys_from_a_file(
    tmp_path: Path,
) -> None:
    keys = tmp_path / "keys"
    keys.write_text("k-from-file-31337\n")
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "ARENA_PORT": "0",
        "ARENA_DEMO": "true",
        "ARENA_RECORD": "false",
        "ARENA_VIEWER_KEYS": "viewer-1",
    }
    with serving(["--api-key-file", str(keys)], cwd=tmp_path, env=env) as served:
        with open(f"/proc/{served.process.pid}/cmdline", "rb") as cmdline:
            assert b"k-from-file-31337" not in cmdline.read()
        robots = f"{served.url}/api/robots"
        assert httpx.get(robots, timeout=10).status_code == 401  # keys are on
        viewer = httpx.get(robots, headers={"Authorization": "Bearer viewer-1"}, timeout=10)
        assert [robot["id"] for robot in viewer.json()] == ["demo-arm"]  # ARENA_DEMO
        refused = httpx.post(
            f"{robots}/demo-arm/reset", headers={"Authorization": "Bearer viewer-1"}, timeout=10
        )
        assert refused.status_code == 403  # a viewer key reads (and e-stops), nothing more
        stopped = httpx.post(
            f"{robots}/demo-arm/estop",
            headers={"Authorization": "Bearer k-from-file-31337"},
            timeout=10,
        )
        assert stopped.status_code == 200
    assert not (tmp_path / "recordings").exists()  # ARENA_RECORD=false
    assert "k-from-file-31337" not in served.log
