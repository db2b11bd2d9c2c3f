"""deploy/secure/: mutual TLS and access control keep every party but the robot, the service and operators out.

On 127.0.0.1 with the deployment's own files: ``make-certs.sh`` makes the CA and the certificates (and one for an
"intruder" signed by the same CA); the zenoh router runs ``router.json5`` in a subprocess; ``objslam serve`` and
``objslam replay`` run with ``service.json5`` and ``robot.json5``; the operator uses ``operator.json5``. Only the
certificate directory and the router's endpoint differ from the compose deployment.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from service.protocol import encode_frame
from tests.conftest import free_port, make_frame

pytestmark = pytest.mark.integration

SECURE = Path(__file__).resolve().parents[1] / "deploy" / "secure"
ROBOT = "robot1"
SECRETS = "/run/secrets/"  # where the compose file mounts the certificates
FRAMES = 10
ROUTER_SCRIPT = """
import sys, zenoh
session = zenoh.open(zenoh.Config.from_file(sys.argv[1]))
print("ready", flush=True)
sys.stdin.read()  # until the test closes stdin (or dies)
session.close()
"""


@dataclass
class Deployment:
    certs: Path
    configs: Path
    endpoint: str

    def config(self, party: str) -> Path:
        return self.configs / f"{party}.json5"

    def session(self, party: str) -> zenoh.Session:
        return zenoh.open(zenoh.Config.from_file(str(self.config(party))))


def _localised(text: str, certs: Path, endpoint: str) -> str:
    """A deployment config with the certificates in ``certs`` and the router at ``endpoint``."""
    assert SECRETS in text and "7447" in text
    text = text.replace(f'"{SECRETS}', f'"{certs}/')
    return text.replace("tls/0.0.0.0:7447", endpoint).replace("tls/zenoh-router:7447", endpoint)


def _stop(process: subprocess.Popen, timeout: float = 20.0) -> str:
    """Stop a subprocess (SIGTERM, then SIGKILL); its output."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
    try:
        out, _ = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        out, _ = process.communicate()
    return out or ""


def _objslam(*args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        [sys.executable, "-m", "service", *args], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )


@pytest.fixture(scope="module")
def deployment(tmp_path_factory):
    """Certificates, the four configs on a free port of 127.0.0.1, and the secured router running."""
    root = tmp_path_factory.mktemp("secure")
    certs = root / "certs"
    for out, robots in ((certs, [ROBOT, "intruder"]), (root / "rogue", [ROBOT])):  # rogue: another CA's robot1
        made = subprocess.run(
            ["sh", str(SECURE / "make-certs.sh"), str(out), *robots], capture_output=True, text=True, timeout=60
        )
        assert made.returncode == 0, made.stderr
    endpoint = f"tls/127.0.0.1:{free_port()}"
    configs = root / "configs"
    configs.mkdir()
    for party in ("router", "service", "robot", "operator"):
        text = (SECURE / f"{party}.json5").read_text()
        (configs / f"{party}.json5").write_text(_localised(text, certs, endpoint))
    robot = (configs / "robot.json5").read_text()
    # a party with a certificate of the deployment's CA, but a common name the router's ACL does not know
    (configs / "intruder.json5").write_text(robot.replace(f"/{ROBOT}.", "/intruder."))
    # robot1's name on a certificate of another CA
    (configs / "rogue.json5").write_text(robot.replace(f"{certs}/{ROBOT}.", f"{root}/rogue/{ROBOT}."))
    router = subprocess.Popen(
        [sys.executable, "-c", ROUTER_SCRIPT, str(configs / "router.json5")],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert router.stdout is not None
        line = router.stdout.readline()
        assert line.strip() == "ready", line + _stop(router)
        yield Deployment(certs, configs, endpoint)
    finally:
        _stop(router, timeout=10)


def _replies(session: zenoh.Session, key: str, timeout: float = 2.0) -> list[bytes]:
    """The payloads of every reply, ok or error."""
    out = []
    for reply in session.get(key, timeout=timeout):
        sample = reply.ok if reply.ok is not None else reply.err
        out.append(sample.payload.to_bytes())
    return out


def _status(session: zenoh.Session) -> dict:
    (reply,) = _replies(session, f"objslam/{ROBOT}/status", timeout=5.0)
    return json.loads(reply)


def _wait_for_status(session: zenoh.Session, serve: subprocess.Popen, deadline_s: float = 30.0) -> dict:
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        assert serve.poll() is None, _stop(serve)
        replies = _replies(session, f"objslam/{ROBOT}/status", timeout=1.0)
        if replies:
            return json.loads(replies[0])
        time.sleep(0.2)
    raise AssertionError("the service never answered the operator's status query")


def _outputs(state: Path) -> list[str]:
    """What the service wrote into its state directory besides its map store (``map.db`` and its WAL files)."""
    return sorted(p.name for p in state.iterdir() if not p.name.startswith("map.db")) if state.exists() else []


def test_the_router_refuses_plain_tcp_and_a_party_without_a_certificate_of_its_ca(deployment):
    rogue = zenoh.Config.from_file(str(deployment.config("rogue")))
    assert "rogue" in rogue.get_json("transport/link/tls/connect_certificate")
    no_cert = zenoh.Config.from_file(str(deployment.config("operator")))
    for key in ("connect_certificate", "connect_private_key"):
        no_cert.insert_json5(f"transport/link/tls/{key}", "null")
    no_cert.insert_json5("transport/link/tls/enable_mtls", "false")
    plain = zenoh.Config()
    plain.insert_json5("mode", '"client"')
    plain.insert_json5("scouting/multicast/enabled", "false")
    plain.insert_json5("connect/endpoints", json.dumps([deployment.endpoint.replace("tls/", "tcp/")]))
    for config in (rogue, no_cert, plain):
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            zenoh.open(config).close()


def test_only_the_robot_puts_frames_and_only_operators_query_and_save(deployment, tmp_path):
    """Frames from the intruder (a CA-signed certificate of an unknown name) and the operator are dropped, saves
    from the intruder and the robot get no reply and write nothing, and the intruder can neither read frames nor
    answer status in the service's place; the operator's status and save work."""
    state = tmp_path / "state"
    serve = _objslam(
        "serve", "--zenoh-config", str(deployment.config("service")), "--robot", ROBOT, "--state-dir", str(state)
    )
    sessions = []
    try:
        operator, intruder, robot = (deployment.session(p) for p in ("operator", "intruder", "robot"))
        sessions += [operator, intruder, robot]
        assert _wait_for_status(operator, serve)["frames_received"] == 0

        # the intruder: frames into robot1's map, saves, then a subscriber to every frame and a fake status
        frames = [encode_frame(make_frame(t=1.0 + i, seq=i, seed=i)) for i in range(FRAMES)]
        for payload in frames:
            intruder.put(f"objslam/{ROBOT}/rgbd", payload)
            intruder.put("objslam/*/rgbd", payload)
        operator.put(f"objslam/{ROBOT}/rgbd", frames[0])  # known, but not a robot
        for key in (f"objslam/{ROBOT}/save", "objslam/**/save", f"objslam/{ROBOT}/status"):
            assert _replies(intruder, key) == [], key
        assert _replies(robot, f"objslam/{ROBOT}/save") == []  # a robot publishes; it does not save
        stolen: list[bytes] = []
        snoop = intruder.declare_subscriber("objslam/**", lambda sample: stolen.append(sample.payload.to_bytes()))
        fake = intruder.declare_queryable(f"objslam/{ROBOT}/status", lambda query: query.reply(query.key_expr, b"{}"))
        time.sleep(1.0)
        status = _status(operator)  # one reply: the service's, not the intruder's
        assert status["robot"] == ROBOT and status["frames_received"] == 0
        assert _outputs(state) == []

        # the robot's replay, with its own certificate
        replay = _objslam(
            "replay",
            f"synthetic:room?seed=0&frames={FRAMES}",
            "--zenoh-config",
            str(deployment.config("robot")),
            "--robot",
            ROBOT,
            "--max-rate",
        )
        out, _ = replay.communicate(timeout=60)
        assert replay.returncode == 0 and f"published {FRAMES} frames" in out, out
        end = time.monotonic() + 30
        while (status := _status(operator))["frames_processed"] + status["frames_rejected_total"] < FRAMES:
            assert time.monotonic() < end, status
            time.sleep(0.2)
        assert status["frames_received"] == FRAMES and status["frames_processed"] == FRAMES, status
        assert stolen == []
        snoop.undeclare()
        fake.undeclare()
        assert _outputs(state) == []

        operator_save = ["save", "--json", "--robot", ROBOT, "--zenoh-config", str(deployment.config("operator"))]
        save = subprocess.run(
            [sys.executable, "-m", "service", *operator_save],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert save.returncode == 0, save.stderr
        saved = json.loads(save.stdout)
        assert saved["robot"] == ROBOT and saved["files"]
        assert set(_outputs(state)) <= set(saved["files"]) and "trajectory.tum" in _outputs(state)  # and map.db
    finally:
        for session in sessions:
            session.close()
        log = _stop(serve)
    assert serve.returncode == 0, log


def test_the_router_acl_denies_by_default_and_grants_frames_to_the_robot_alone():
    """router.json5 as zenoh reads it: deny by default, and put on a robot's frames only in the robot's policy."""
    acl = json.loads(zenoh.Config.from_file(str(SECURE / "router.json5")).get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {rule["id"]: rule for rule in acl["rules"]}
    subjects = {subject["id"]: subject for subject in acl["subjects"]}
    assert all(rule["permission"] == "allow" for rule in rules.values())
    frame_putters = set()
    for policy in acl["policies"]:
        for rule in map(rules.get, policy["rules"]):
            puts = "put" in rule["messages"] and "ingress" in rule["flows"]
            if puts and any(key.endswith("/rgbd") for key in rule["key_exprs"]):
                assert rule["key_exprs"] == [f"objslam/{ROBOT}/rgbd"]
                frame_putters |= {cn for s in policy["subjects"] for cn in subjects[s]["cert_common_names"]}
    assert frame_putters == {ROBOT}
    for subject in subjects.values():  # every party is known by a certificate, never by a wildcard subject
        assert subject.get("cert_common_names")
