"""deploy/: the compose file and the Dockerfile are consistent with each other and with the objslam CLI.

No Docker engine runs here, so every command line is parsed by the real typer app (an unknown flag or a
bad value fails) and the effective settings of each container are built from its environment and flags.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import tomllib
from pathlib import Path

import pytest
import typer.main
import yaml

from service.cli import _settings, app
from service.config import ConfigError, Settings
from sources import open_dataset

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
ROUTER = "zenoh-router"


def _compose() -> dict:
    return yaml.safe_load((DEPLOY / "docker-compose.yml").read_text())


def _dockerfile() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs, continuation lines joined, comments dropped."""
    text = re.sub(r"\\\n", " ", (DEPLOY / "Dockerfile").read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def _instructions(name: str) -> list[str]:
    return [rest for word, rest in _dockerfile() if word == name]


def _image_env() -> dict[str, str]:
    env = {}
    for rest in _instructions("ENV"):
        env.update(token.split("=", 1) for token in shlex.split(rest))
    return env


def _healthcheck() -> tuple[dict[str, str], list[str]]:
    (rest,) = _instructions("HEALTHCHECK")
    options, _, command = rest.partition(" CMD ")
    return dict(o.lstrip("-").split("=", 1) for o in options.split()), json.loads(command)


def parse_invocation(args: list[str]):
    """The click context of ``objslam ARGS`` as the real app parses it (without running it)."""
    command = typer.main.get_command(app)
    ctx = command.make_context("objslam", list(args), resilient_parsing=False)
    while hasattr(command, "resolve_command"):  # a group: descend into the sub-command
        rest = [*getattr(ctx, "_protected_args", getattr(ctx, "protected_args", [])), *ctx.args]
        name, command, rest = command.resolve_command(ctx, rest)
        ctx = command.make_context(name, rest, parent=ctx)
    return ctx


def effective_settings(args: list[str], env: dict[str, str], monkeypatch) -> tuple[str, dict, Settings]:
    """(command, parsed parameters, settings) of ``objslam ARGS`` run with exactly ``env`` as OBJSLAM_* variables."""
    ctx = parse_invocation(args)
    for key in [k for k in os.environ if k.startswith("OBJSLAM_")]:
        monkeypatch.delenv(key)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    p = ctx.params
    settings = _settings(
        p.get("config"), p.get("robot"), p.get("connect"), p.get("listen"), p.get("mode"), p.get("state_dir")
    )
    return ctx.info_name, p, settings


def _containers() -> dict[str, tuple[list[str], dict[str, str]]]:
    """Each objslam container of the deployment: (objslam arguments, environment)."""
    compose = _compose()["services"]
    (entrypoint,) = _instructions("ENTRYPOINT")
    assert json.loads(entrypoint) == ["objslam"]
    image = _image_env()
    containers = {
        name: (compose[name]["command"], {**image, **compose[name].get("environment", {})})
        for name in ("objslam", "replay")
    }
    containers["objslam healthcheck"] = (_healthcheck()[1][1:], containers["objslam"][1])
    containers["image default"] = (json.loads(_instructions("CMD")[0]), image)
    containers["image healthcheck"] = (_healthcheck()[1][1:], image)
    return containers


def _router_ports() -> set[int]:
    command = _compose()["services"][ROUTER]["command"]
    listen = [command[i + 1] for i, arg in enumerate(command) if arg in ("--listen", "-l")]
    assert listen, "the router listens on no endpoint"
    return {int(endpoint.rsplit(":", 1)[1]) for endpoint in listen}


def test_compose_file_has_the_router_the_service_and_a_replay_client():
    services = _compose()["services"]
    assert {ROUTER, "objslam", "replay"} <= set(services)
    for name in ("objslam", "replay"):
        build = services[name]["build"]
        assert (DEPLOY / build["context"] / build["dockerfile"]).resolve() == DEPLOY / "Dockerfile"
    assert ROUTER in services["objslam"]["depends_on"]
    assert services["replay"]["depends_on"]["objslam"]["condition"] == "service_healthy"
    assert services["replay"]["healthcheck"]["disable"] is True  # a one-shot client would never be healthy


def test_router_is_the_official_zenoh_image_at_the_version_objslam_pins():
    image, _, tag = _compose()["services"][ROUTER]["image"].partition(":")
    assert image == "eclipse/zenoh"
    pins = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert f"eclipse-zenoh=={tag}" in pins
    published = {int(p.rsplit(":", 1)[1]) for p in _compose()["services"][ROUTER]["ports"]}
    assert published <= _router_ports()


@pytest.mark.parametrize(
    "container", ["objslam", "replay", "objslam healthcheck", "image default", "image healthcheck"]
)
def test_every_command_line_is_valid_and_reaches_the_router(container, monkeypatch):
    args, env = _containers()[container]
    command, params, settings = effective_settings(args, env, monkeypatch)
    assert command in ("serve", "replay", "status")
    assert settings.zenoh.mode == "client"  # clients of the router: nothing else listens
    assert settings.zenoh.connect, "connects to nothing"
    for endpoint in settings.zenoh.connect:
        proto, host, port = re.fullmatch(r"(\w+)/([\w.-]+):(\d+)", endpoint).groups()
        assert (proto, host) == ("tcp", ROUTER) and int(port) in _router_ports()
    if command == "replay":
        assert len(open_dataset(params["dataset"])) > 0


def test_service_healthcheck_and_replay_use_one_robot(monkeypatch):
    robots = {name: effective_settings(args, env, monkeypatch)[2].robot for name, (args, env) in _containers().items()}
    assert robots["objslam"] == robots["objslam healthcheck"] == robots["replay"]
    assert robots["image default"] == robots["image healthcheck"]


@pytest.mark.parametrize(
    "args",
    [
        ["serve", "--bogus"],
        ["replay"],
        ["status", "maps"],
        ["serve", "--rate", "3"],
        ["serve", "--mode", "clinet"],
        ["bench", "nothing"],
    ],
)
def test_the_invocation_check_fails_on_a_bad_command_line(args, monkeypatch):
    with pytest.raises(Exception) as info:
        effective_settings(args, {}, monkeypatch)
    assert hasattr(info.value, "exit_code") or isinstance(info.value, ConfigError)


def test_image_runs_as_a_non_root_user_with_a_status_healthcheck():
    users = _instructions("USER")
    assert users and users[-1] not in ("root", "0")
    (useradd,) = [r for r in _instructions("RUN") if "useradd" in r]
    assert re.search(rf"--uid (\d+) {users[-1]}\b", useradd).group(1) != "0"
    options, command = _healthcheck()
    assert command[:2] == ["objslam", "status"]
    seconds = float(options["timeout"].rstrip("s"))
    assert seconds > Settings().zenoh.query_timeout_s  # the query gives up before docker does


def test_state_volume_is_owned_by_the_service_user():
    service = _compose()["services"]["objslam"]
    state_dir = service["command"][service["command"].index("--state-dir") + 1]
    assert f"objslam-state:{state_dir}" in service["volumes"] and "objslam-state" in _compose()["volumes"]
    user = _instructions("USER")[-1]
    assert any(re.search(rf"chown {user}(:{user})? {state_dir}\b", r) for r in _instructions("RUN"))
    assert json.loads(_instructions("VOLUME")[0]) == [state_dir]


def test_image_copies_every_package_onto_the_pinned_python():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    copied = {rest.split()[0] for rest in _instructions("COPY")} | {
        name for rest in _instructions("COPY") for name in rest.split()[:-1]
    }
    packages = {p.rstrip("*") for p in project["tool"]["setuptools"]["packages"]["find"]["include"]}
    assert packages <= copied and {"pyproject.toml", "README.md", "models"} <= copied
    assert all((ROOT / name).exists() for name in copied)
    (base,) = _instructions("FROM")
    version = re.fullmatch(r"python:(\d+\.\d+)-slim", base).group(1)
    assert f">={version}" in project["project"]["requires-python"]


def test_secure_compose_command_lines_are_valid_and_reach_the_tls_router_with_their_own_certificates(monkeypatch):
    """deploy/secure/: each objslam command line (and the image's healthcheck, and `run operator save`) parses, its
    zenoh config file is mounted from deploy/secure/, connects over tls to a port the router listens on, and reads
    only certificates mounted into its own container; the router accepts tls with client certificates only."""
    import zenoh

    secure = DEPLOY / "secure"
    services = yaml.safe_load((secure / "docker-compose.yml").read_text())["services"]
    assert services[ROUTER]["image"] == _compose()["services"][ROUTER]["image"]

    def config_of(name: str, path: str) -> zenoh.Config:
        mounts = dict(v.split(":")[1::-1] for v in services[name].get("volumes", []) if v.startswith("./"))
        assert path in mounts, f"{name}: {path} is not mounted"
        conf = zenoh.Config.from_file(str(secure / mounts[path]))
        tls = json.loads(conf.get_json("transport/link/tls"))
        files = {tls[k] for k in tls if k.endswith(("certificate", "private_key")) and tls[k] is not None}
        assert json.loads(conf.get_json("transport/link/protocols")) == ["tls"] and tls["enable_mtls"] is True
        assert {f"/run/secrets/{s}" for s in services[name]["secrets"]} == files, name
        return conf

    router = config_of(ROUTER, services[ROUTER]["command"][services[ROUTER]["command"].index("-c") + 1])
    ports = {int(e.rsplit(":", 1)[1]) for e in json.loads(router.get_json("listen/endpoints"))}
    assert all(e.startswith("tls/") for e in json.loads(router.get_json("listen/endpoints")))
    image, service_env = _image_env(), services["objslam"]["environment"]
    containers = {
        "objslam": (services["objslam"]["command"], service_env),
        "objslam healthcheck": (_healthcheck()[1][1:], service_env),
        "replay": (services["replay"]["command"], services["replay"]["environment"]),
        "operator": (services["operator"]["command"], services["operator"]["environment"]),
        "operator save": (["save"], services["operator"]["environment"]),
    }
    robots = set()
    for container, (args, env) in containers.items():
        command, params, settings = effective_settings(args, {**image, **env}, monkeypatch)
        # effective_settings leaves --zenoh-config out of the settings: the flag and the environment must agree
        flag, from_env = params.get("zenoh_config"), settings.zenoh.config_file
        assert (flag or from_env) and (flag is None or from_env is None or flag == from_env), container
        conf = config_of(container.split()[0], str(flag or from_env))
        assert settings.zenoh.mode == "client" == json.loads(conf.get_json("mode")), container
        for endpoint in [*settings.zenoh.connect, *json.loads(conf.get_json("connect/endpoints"))]:
            proto, host, port = re.fullmatch(r"(\w+)/([\w.-]+):(\d+)", endpoint).groups()
            assert (proto, host) == ("tls", ROUTER) and int(port) in ports, container
        if command == "replay":
            assert len(open_dataset(params["dataset"])) > 0
        robots.add(settings.robot)
    assert robots == {"robot1"}
