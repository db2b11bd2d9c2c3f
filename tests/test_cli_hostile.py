"""Hostile input to the command line and faults on the shutdown path (issue 26, "CLI" and "Faults").

Every mistake in flags, files or environment is one line on stderr and a non-zero exit before any work; a
reply is printed as data, never as markup; the outputs of an empty map are written, and on SIGTERM every
output file that can be written is, with the exit code saying whether some could not.
"""

from __future__ import annotations

import io
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from rich.console import Console

from bench.rig import client as client_session
from graph.trajectory import Trajectory
from service.client import query, render_reply
from service.config import ConfigError, check_environment, load_settings
from service.outputs import EXIT_OUTPUTS_FAILED, OutputsError, check_output_dir, run_summary, write_outputs
from service.summary import print_summary
from tests.conftest import free_port

OUTPUTS = ["cloud.npy", "loops.json", "map.png", "objects.json", "odometry.tum", "report.md", "trajectory.tum"]


def _objslam(*args: str, env: dict[str, str] | None = None, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "service", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, **(env or {})},
    )


def _one_error_line(cli: subprocess.CompletedProcess, *words: str) -> str:
    """The single ``objslam: error:`` line of a failed command (no traceback), checked to contain ``words``."""
    lines = cli.stderr.strip().splitlines()
    assert cli.returncode != 0, cli.stdout
    assert len(lines) == 1 and lines[0].startswith("objslam: error: "), cli.stderr
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


# ------------------------------------------------------------------ configuration


@pytest.mark.parametrize(
    ("text", "where"),
    [
        ("ingest:\n  queue_sise: 5\n", "ingest.queue_sise"),
        ("zenoh:\n  modee: client\n", "zenoh.modee"),
        ("persistence:\n  keepp: 4\n", "persistence.keepp"),
        ("camera:\n  fxx: 500\n", "camera.fxx"),
        ("robott: r2\n", "robott"),
    ],
)
def test_an_unknown_key_in_any_section_of_the_file_is_an_error_naming_it(tmp_path, text, where):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    with pytest.raises(ConfigError, match=rf"^invalid configuration at {where}: unknown key$"):
        load_settings(cfg)


def test_an_unknown_key_given_as_a_flag_override_is_an_error_too():
    with pytest.raises(ConfigError, match=r"at zenoh\.bogus: unknown key"):
        load_settings(None, {"zenoh": {"bogus": 1}})


@pytest.mark.parametrize("name", ["OBJSLAM_ROBOTT", "OBJSLAM_INGEST__QUEUE_SISE", "OBJSLAM_ZENOH__MODEE", "OBJSLAM_"])
def test_an_unknown_objslam_environment_variable_is_an_error_naming_it(monkeypatch, name):
    monkeypatch.setenv(name, "5")
    with pytest.raises(ConfigError, match=f"unknown environment variable {name}:"):
        load_settings()


def test_the_environment_variables_of_the_tests_ci_and_deployment_are_known():
    check_environment(
        {
            "OBJSLAM_ROBOT": "robot1",
            "OBJSLAM_ZENOH__MODE": "client",
            "OBJSLAM_ZENOH__CONNECT": '["tcp/zenoh-router:7447"]',
            "OBJSLAM_ZENOH__QUERY_TIMEOUT_S": "1",
            "OBJSLAM_ZENOH": '{"mode": "client"}',
            "OBJSLAM_INGEST__QUEUE_SIZE": "512",
            "OBJSLAM_PERSISTENCE__EVERY_KEYFRAMES": "5",
            "OBJSLAM_OBJECTS__LANDMARKS": "false",
            "OBJSLAM_LOOPS__SOURCE": "policy",
            "OBJSLAM_LOOPS__POLICY": "models/lc/room_seed3.onnx",
            "OBJSLAM_DETECTOR__CLASS_THRESHOLDS": '{"cup": 0.3}',
            "OBJSLAM_DETECTOR__CLASS_THRESHOLDS__CUP": "0.3",
            "PATH": "/usr/bin",
        }
    )


@pytest.mark.parametrize(("text", "kind"), [("- a\n- b\n", "list"), ("42\n", "int"), ("just words\n", "str")])
def test_a_file_whose_top_level_is_not_a_mapping_is_one_clear_error(tmp_path, text, kind):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    with pytest.raises(ConfigError, match=f"top level must be a mapping of sections .* not {kind}"):
        load_settings(cfg)


def test_an_empty_file_is_no_sections(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("")
    assert load_settings(cfg).robot == "robot1"


def test_a_section_variable_that_is_not_json_is_one_clear_error(monkeypatch):
    monkeypatch.setenv("OBJSLAM_ZENOH", "notjson")
    with pytest.raises(ConfigError, match=r"invalid environment: .*zenoh.*OBJSLAM_ZENOH__MODE=client"):
        load_settings()


@pytest.mark.parametrize("prefix", ["", "a/*", "a/**", "a b", "/a", "a/", "a//b", "a$b", "x#", "q?x"])
def test_a_key_prefix_that_is_no_zenoh_key_is_refused(prefix):
    with pytest.raises(ConfigError, match=r"^invalid configuration at zenoh\.key_prefix: .* is not a zenoh key"):
        load_settings(None, {"zenoh": {"key_prefix": prefix}})


def test_a_key_prefix_of_several_chunks_is_a_valid_key():
    settings = load_settings(None, {"zenoh": {"key_prefix": "site-2/objslam_v1.0"}, "robot": "r1"})
    assert settings.key_prefix == "site-2/objslam_v1.0/r1"
    zenoh.KeyExpr(f"{settings.key_prefix}/rgbd")  # zenoh agrees


@pytest.mark.parametrize("value", [0, -1, float("nan"), float("inf")])
def test_a_query_timeout_must_be_positive_and_finite(value):
    with pytest.raises(ConfigError, match=r"zenoh\.query_timeout_s"):
        load_settings(None, {"zenoh": {"query_timeout_s": value}})


@pytest.mark.parametrize(
    ("args", "env", "words"),
    [
        (["replay", "synthetic:room?frames=2", "--rate", "nan"], {}, ["--rate", "nan"]),
        (["replay", "synthetic:room?frames=2", "--rate", "inf"], {}, ["--rate", "inf"]),
        (["save", "--timeout", "nan"], {}, ["--timeout"]),
        (["config"], {"OBJSLAM_ROBOTT": "x"}, ["OBJSLAM_ROBOTT"]),
        (["config"], {"OBJSLAM_ZENOH": "notjson"}, ["OBJSLAM_ZENOH"]),
        (["status"], {"OBJSLAM_ZENOH__KEY_PREFIX": ""}, ["zenoh.key_prefix"]),
    ],
)
def test_the_command_line_says_what_is_wrong_in_one_line(args, env, words):
    _one_error_line(_objslam(*args, env=env), *words)


def test_a_config_file_that_is_a_list_fails_the_command_in_one_line(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("- robot: r2\n")
    _one_error_line(_objslam("config", "--config", str(cfg)), "top level", "list")


# ------------------------------------------------------------------ run --out


def test_out_must_be_a_directory_or_creatable(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(NotADirectoryError, match="is a file"):
        check_output_dir(afile)
    with pytest.raises(NotADirectoryError, match="cannot be created"):
        check_output_dir(afile / "sub" / "dir")
    check_output_dir(tmp_path / "new" / "dir")  # creatable
    check_output_dir(tmp_path)
    assert not (tmp_path / "new").exists()  # checked, not created


def test_run_into_an_existing_file_fails_before_any_work(tmp_path):
    afile = tmp_path / "out"
    afile.write_text("keep me")
    started = time.monotonic()
    cli = _objslam("run", "synthetic:room?seed=0&frames=400", "--out", str(afile))
    _one_error_line(cli, "--out", "is a file")
    assert time.monotonic() - started < 30  # 400 frames would take minutes
    assert afile.read_text() == "keep me"


# ------------------------------------------------------------------ replay and queries over zenoh


def test_replay_with_no_subscriber_on_its_key_fails_in_one_line(router):
    _, endpoint = router
    cli = _objslam(
        "replay",
        "synthetic:room?frames=2",
        "--max-rate",
        "--mode",
        "client",
        "--connect",
        endpoint,
        env={"OBJSLAM_ZENOH__QUERY_TIMEOUT_S": "1"},
    )
    _one_error_line(cli, "no subscriber on objslam/robot1/rgbd within 1 s")
    assert "published" not in cli.stdout


def _client_settings(endpoint: str, timeout: float):
    return load_settings(None, {"zenoh": {"mode": "client", "connect": [endpoint], "query_timeout_s": timeout}})


def test_no_reply_waits_the_whole_timeout_it_names(router):
    _, endpoint = router
    started = time.monotonic()
    with pytest.raises(TimeoutError, match=r"no reply on objslam/robot1/status within 1\.5 s"):
        query(_client_settings(endpoint, 1.5), "status")
    assert 1.5 <= time.monotonic() - started < 4.0


def _answering(endpoint: str, key: str, body: dict) -> zenoh.Session:
    """A client session of the router answering ``key`` with ``body`` (a service, or a rogue peer)."""
    session = client_session(endpoint)
    session.declare_queryable(key, lambda q: q.reply(q.key_expr, json.dumps(body).encode()))
    return session


def test_replies_from_two_services_are_reported_without_waiting_the_whole_timeout(router, caplog):
    _, endpoint = router
    key = "objslam/robot1/status"
    sessions = [_answering(endpoint, key, {"robot": "robot1", "service_id": sid}) for sid in ("aaa1", "bbb2")]
    try:
        time.sleep(0.3)  # the router learns both queryables
        started = time.monotonic()
        with caplog.at_level(logging.WARNING, logger="service.client"):
            reply = query(_client_settings(endpoint, 5.0), "status")
        assert time.monotonic() - started < 2.0
    finally:
        for session in sessions:
            session.close()
    assert reply["service_id"] in ("aaa1", "bbb2")
    warning = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warning) == 1 and "2 replies" in warning[0] and "aaa1" in warning[0] and "bbb2" in warning[0]


def test_a_single_service_answers_without_warning(router, caplog):
    _, endpoint = router
    session = _answering(endpoint, "objslam/robot1/loops", {"robot": "robot1", "service_id": "aaa1", "loops": []})
    try:
        time.sleep(0.3)
        with caplog.at_level(logging.WARNING, logger="service.client"):
            assert query(_client_settings(endpoint, 5.0), "loops")["loops"] == []
    finally:
        session.close()
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_an_error_reply_or_a_reply_that_is_no_json_object_is_one_clear_error(router):
    _, endpoint = router
    session = client_session(endpoint)
    session.declare_queryable("objslam/robot1/objects", lambda q: q.reply_err(b'{"error": "busy"}'))
    session.declare_queryable("objslam/robot1/loops", lambda q: q.reply(q.key_expr, b"[1, 2]"))
    try:
        time.sleep(0.3)
        with pytest.raises(RuntimeError, match=r"objslam/robot1/objects: service replied with an error: .*busy"):
            query(_client_settings(endpoint, 5.0), "objects")
        with pytest.raises(RuntimeError, match="not a JSON object"):
            query(_client_settings(endpoint, 5.0), "loops")
    finally:
        session.close()


def test_a_reply_is_printed_as_plain_text_never_as_markup():
    out = io.StringIO()
    console = Console(file=out, width=200)
    hostile = "[/x] [bold]b[/bold] [link=file:///etc]"
    reply = {
        "robot": hostile,
        hostile: hostile,
        "latency": {hostile: {"n": 1, "p50_ms": hostile, "p95_ms": 1, "p99_ms": 1, "max_ms": 1}},
    }
    render_reply(console, "status", reply)
    render_reply(console, "objects", {"objects": [{"label": hostile}]})
    render_reply(console, "trajectory", {"format": hostile, "poses": [[1.0, hostile]]})
    assert out.getvalue().count("[/x]") >= 6


# ------------------------------------------------------------------ outputs of an empty map, failing writes


def _empty() -> Trajectory:
    return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))


def _empty_status() -> dict:
    return {
        "frames_processed": 0,
        "frames_rejected": {},
        "frames_dropped": 0,
        "keyframes": 0,
        "poses": 0,
        "loop_closures": {"accepted": 0, "rejected": 0},
        "latency": {},
    }


def test_the_outputs_of_an_empty_map_are_written(tmp_path):
    summary = run_summary("[/empty]", 0, 0.0, _empty_status())
    summary = write_outputs(tmp_path, _empty(), _empty(), summary, None, [], [], np.zeros((0, 3), np.float32))
    assert sorted(p.name for p in tmp_path.iterdir()) == OUTPUTS
    assert (tmp_path / "trajectory.tum").read_text().splitlines() == ["# timestamp tx ty tz qx qy qz qw"]
    assert json.loads((tmp_path / "objects.json").read_text()) == []
    assert "No frame was processed" in (tmp_path / "report.md").read_text()
    out = io.StringIO()
    print_summary(Console(file=out, width=200), summary, tmp_path)  # the dataset's name is no markup either
    assert "[/empty]" in out.getvalue()


def test_one_failing_output_file_leaves_the_others_written(tmp_path, caplog):
    (tmp_path / "trajectory.tum" / "in_the_way").mkdir(parents=True)  # blocks even root's rename
    summary = run_summary("blocked", 0, 0.0, _empty_status())
    with caplog.at_level(logging.ERROR, logger="service.outputs"), pytest.raises(OutputsError) as failure:
        write_outputs(tmp_path, _empty(), _empty(), summary, None, [], [], np.zeros((0, 3), np.float32))
    assert list(failure.value.failed) == ["trajectory.tum"] and "trajectory.tum" in str(failure.value)
    assert all((tmp_path / name).is_file() for name in OUTPUTS if name != "trajectory.tum")
    assert [r.getMessage() for r in caplog.records if "trajectory.tum" in r.getMessage()]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary file left behind


def test_save_on_an_empty_map_writes_the_outputs(tmp_path):
    from service.node import ServiceNode
    from service.zenoh_session import open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = load_settings(
        None, {"state_dir": tmp_path, "robot": "empty", "zenoh": {"listen": [endpoint]}, "detector": {"enabled": False}}
    )
    session = open_session(settings.zenoh, "server")
    node = ServiceNode(settings, session)
    try:
        node.start()
        reply = query(_client_settings(endpoint, 30.0).model_copy(update={"robot": "empty"}), "save")
    finally:
        node.stop()
        session.close()
    assert reply["frames_processed"] == 0 and reply["keyframes"] == 0
    assert set(OUTPUTS) <= set(reply["files"])


def _serve_until_sigterm(state: Path) -> tuple[int, str]:
    """``objslam serve --state-dir state`` started, stopped by SIGTERM once it serves: (exit code, its log)."""
    args = ["serve", "--listen", f"tcp/127.0.0.1:{free_port()}", "--state-dir", str(state), "--lc-source", "off"]
    serve = subprocess.Popen(
        [sys.executable, "-m", "service", *args],
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "OBJSLAM_DETECTOR__ENABLED": "false"},
    )
    assert serve.stderr is not None
    log = []
    for line in serve.stderr:  # until it serves (or exits)
        log.append(line)
        if "objslam serve: robot" in line:
            break
    serve.send_signal(signal.SIGTERM)
    try:
        _, rest = serve.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        serve.kill()
        _, rest = serve.communicate()
    return serve.returncode, "".join(log) + rest


def test_sigterm_on_an_empty_map_writes_the_outputs_and_exits_0(tmp_path):
    code, log = _serve_until_sigterm(tmp_path / "state")
    assert code == 0 and "Traceback" not in log, log
    assert all((tmp_path / "state" / name).is_file() for name in OUTPUTS)


def test_sigterm_writes_every_output_it_can_and_exits_3_when_one_fails(tmp_path):
    state = tmp_path / "state"
    (state / "map.png" / "in_the_way").mkdir(parents=True)
    code, log = _serve_until_sigterm(state)
    assert code == EXIT_OUTPUTS_FAILED == 3 and "Traceback" not in log, log
    assert all((state / name).is_file() for name in OUTPUTS if name != "map.png")
    assert len([line for line in log.splitlines() if "could not write" in line and "map.png" in line]) >= 1


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only directory: chmod cannot make it fail")
def test_a_read_only_state_dir_fails_every_output_with_one_line_each(tmp_path):
    tmp_path.chmod(0o555)
    try:
        summary = run_summary("read-only", 0, 0.0, _empty_status())
        with pytest.raises(OutputsError) as failure:
            write_outputs(tmp_path / "out", _empty(), _empty(), summary, None, [], [], np.zeros((0, 3), np.float32))
    finally:
        tmp_path.chmod(0o755)
    assert sorted(failure.value.failed) == OUTPUTS
