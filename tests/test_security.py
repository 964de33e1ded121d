"""Security settings: their translation into Zenoh's configuration, and a TLS router with users and access rules
that keeps out clients without credentials while a whole deployment runs through it."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
import zenoh
from conftest import CLI

from mocapflow.io.markers import read_markers
from mocapflow.runtime.security import SecurityError, SecuritySettings, access_control, load_security
from mocapflow.runtime.session import zenoh_config

PASSWORDS = {"lab": "s3cret-lab", "viewer": "s3cret-viewer", "guest": "s3cret-guest"}


def test_settings_become_zenoh_keys(tmp_path: Path) -> None:
    (tmp_path / "certs").mkdir()
    for name in ("ca.pem", "router.pem", "router-key.pem"):
        (tmp_path / "certs" / name).write_text("-")
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump({
        "tls": {"ca": "certs/ca.pem", "certificate": "certs/router.pem", "key": "certs/router-key.pem"},
        "login": {"user": "lab", "password": "pw"},
        "users": {"viewer": "vpw"},
        "access": {"rules": [{"users": ["viewer"], "allow": ["subscribe"], "deny": ["publish"]}]},
    }))
    settings = load_security(path)
    client = settings.zenoh_keys("client")
    assert client == {
        "transport/link/tls/root_ca_certificate": str(tmp_path / "certs" / "ca.pem"),  # relative to the file
        "transport/link/tls/verify_name_on_connect": True,
        "transport/auth/usrpwd/user": "lab",
        "transport/auth/usrpwd/password": "pw",
    }
    with settings.users_dictionary() as users_file:
        router = settings.zenoh_keys("router", users_file)
        # the router also accepts its own login, so one file can serve a whole lab
        assert users_file.read_text().splitlines() == ["viewer:vpw", "lab:pw"]
        assert users_file.stat().st_mode & 0o777 == 0o600
    assert not users_file.exists()
    assert router["transport/link/tls/listen_certificate"] == str(tmp_path / "certs" / "router.pem")
    assert router["transport/link/tls/listen_private_key"] == str(tmp_path / "certs" / "router-key.pem")
    assert "transport/auth/usrpwd/user" not in router
    acl = router["access_control"]
    assert acl["default_permission"] == "deny" and acl["subjects"] == [{"id": "subject0", "usernames": ["viewer"]}]
    by_id = {r["id"]: r for r in acl["rules"]}
    assert by_id["rule0-allow-ingress"]["messages"] == ["declare_subscriber"]
    assert by_id["rule0-allow-egress"]["messages"] == ["put", "delete"]  # what a subscriber receives
    assert by_id["rule0-deny-ingress"]["messages"] == ["put", "delete"]  # what a publisher sends
    assert all(r["key_exprs"] == ["mocapflow/**"] for r in acl["rules"])
    assert acl["policies"] == [{"id": "policy0", "rules": list(by_id), "subjects": ["subject0"]}]
    config = zenoh_config("client", connect=["tls/127.0.0.1:7447"], security=settings)
    assert json.loads(config.get_json("transport/auth/usrpwd/user")) == "lab"


def test_every_action_maps_to_zenoh_messages() -> None:
    acl = access_control(SecuritySettings.model_validate({"access": {"rules": [{"allow": ["all"]}]}}).access)
    ingress, egress = (set(r["messages"]) for r in acl["rules"])
    assert ingress == {"put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
                       "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"}
    assert egress == {"put", "delete", "declare_subscriber", "reply", "declare_queryable", "query", "liveliness_token"}
    assert acl["subjects"] == [{"id": "subject0"}]  # no users: every authenticated user


def test_bad_settings_are_reported(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("tls: {ca: missing.pem}\n")
    with pytest.raises(SecurityError, match="tls.ca: .*missing.pem does not exist"):
        load_security(path)
    path.write_text("users: {lab: pw}\naccess: {rules: [{users: [lab]}]}\n")
    with pytest.raises(SecurityError, match="access.rules.0: .*'allow' or 'deny'"):
        load_security(path)
    path.write_text("tls: {ca: c.pem}\nlogin: {user: lab}\n")
    with pytest.raises(SecurityError, match="login.password: Field required"):
        load_security(path)


# -- a secured router, in its own process ---------------------------------------------------------------------------
def make_certificates(folder: Path) -> None:
    """A CA and a router certificate for 127.0.0.1 and localhost, made with the openssl command."""
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is needed to make test certificates")
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    (folder / "san.cnf").write_text("subjectAltName=IP:127.0.0.1,DNS:localhost\n")
    for args in (
        ["req", "-x509", *ec, "-keyout", "ca-key.pem", "-out", "ca.pem", "-days", "2", "-subj", "/CN=mocapflow lab CA"],
        ["req", *ec, "-keyout", "router-key.pem", "-out", "router.csr", "-subj", "/CN=localhost"],
        ["x509", "-req", "-in", "router.csr", "-CA", "ca.pem", "-CAkey", "ca-key.pem", "-CAcreateserial",
         "-out", "router.pem", "-days", "2", "-extfile", "san.cnf"],
    ):
        subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True)


def documented_access() -> dict:
    """The access rules of docs/lab-deployment.md's example settings file, as printed there."""
    doc = (Path(__file__).resolve().parents[1] / "docs" / "lab-deployment.md").read_text()
    example = yaml.safe_load(doc.split("## Security settings")[1].split("```yaml")[1].split("```")[0])
    return example["access"]


@pytest.fixture
def secured(tmp_path: Path, free_endpoint: str) -> Iterator[tuple[str, Path]]:
    """A router on tls/ with the documented access rules: users lab (everything on mocapflow/** and
    mocapflow-control/**), viewer (subscribe, query, watch on mocapflow/**) and guest (nothing); one settings file
    per user in ``tmp_path``."""
    make_certificates(tmp_path)
    (tmp_path / "router.yaml").write_text(yaml.safe_dump({
        "tls": {"ca": "ca.pem", "certificate": "router.pem", "key": "router-key.pem"},
        "users": PASSWORDS,
        "access": documented_access(),
    }))
    for user, password in PASSWORDS.items():
        (tmp_path / f"{user}.yaml").write_text(yaml.safe_dump(
            {"tls": {"ca": "ca.pem"}, "login": {"user": user, "password": password}}))
    (tmp_path / "anonymous.yaml").write_text(yaml.safe_dump({"tls": {"ca": "ca.pem"}}))
    endpoint = free_endpoint.replace("tcp/", "tls/")
    log = tmp_path / "router.log"
    with log.open("wb") as out:
        router = subprocess.Popen([*CLI, "router", "--listen", endpoint, "--config",
                                   str(tmp_path / "router.yaml")], stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 20
        while "listening" not in log.read_text():
            assert time.monotonic() < deadline and router.poll() is None, log.read_text()
            time.sleep(0.05)
        assert "(TLS, 3 user(s), access control)" in log.read_text()
        yield endpoint, tmp_path
    finally:
        router.send_signal(signal.SIGTERM)
        router.wait(timeout=20)


def try_open(endpoint: str, settings_file: Path | None) -> zenoh.Session | None:
    """A client session as mocapflow would open it, but giving up after a second instead of retrying forever."""
    settings = load_security(settings_file) if settings_file else None
    config = zenoh_config("client", connect=[endpoint], security=settings)
    config.insert_json5("connect/timeout_ms", "1000")
    try:
        return zenoh.open(config)
    except zenoh.ZError:
        return None


def deliveries(publisher: zenoh.Session, subscriber: zenoh.Session, key: str = "mocapflow/t/x/markers") -> int:
    """How many of 5 samples published by ``publisher`` (with a declared publisher, as nodes do) reach a subscriber
    declared by ``subscriber``."""
    got = []
    with subscriber.declare_subscriber(key, lambda s: got.append(s)), publisher.declare_publisher(key) as pub:
        time.sleep(0.3)
        for i in range(5):
            pub.put(str(i))
        time.sleep(0.5)
    return len(got)


@pytest.mark.integration
def test_clients_without_credentials_can_neither_subscribe_nor_publish(secured: tuple[str, Path]) -> None:
    endpoint, folder = secured
    lab, viewer, guest = (try_open(endpoint, folder / f"{u}.yaml") for u in ("lab", "viewer", "guest"))
    lab2 = try_open(endpoint, folder / "lab.yaml")
    assert lab and viewer and guest and lab2
    try:
        assert deliveries(lab, lab2) == 5  # the credentials work: data flows through the TLS router
        # No session at all without a login, with a wrong password, or without TLS.
        assert try_open(endpoint, folder / "anonymous.yaml") is None
        wrong = folder / "wrong.yaml"
        wrong.write_text(yaml.safe_dump({"tls": {"ca": "ca.pem"}, "login": {"user": "lab", "password": "guess"}}))
        assert try_open(endpoint, wrong) is None
        assert try_open(endpoint.replace("tls/", "tcp/"), folder / "lab.yaml") is None
        # Authenticated but granted nothing: neither subscribes nor publishes.
        assert deliveries(lab, guest) == 0 and deliveries(guest, lab) == 0
        # A viewer may watch, not publish.
        assert deliveries(lab, viewer) == 5 and deliveries(viewer, lab) == 0
        # Rules hold on their keys only: nothing outside mocapflow/** even for the lab user.
        assert deliveries(lab, lab2, "elsewhere/x") == 0
    finally:
        for session in (lab, viewer, guest, lab2):
            session.close()


@pytest.mark.integration
def test_a_deployment_runs_through_the_secured_router(secured: tuple[str, Path]) -> None:
    endpoint, folder = secured
    frames = 2 * 240 + 1
    (folder / "g.yaml").write_text(f"""
name: secured
nodes:
  tracker: {{plugin: simulator, config: {{rig: human, rate: 240, frames: {frames}}}, machine: cam}}
  recorder: {{plugin: recorder, inputs: {{markers: tracker/markers}}, config: {{path: {folder / 'out.c3d'}}}}}
""")
    lab = str(folder / "lab.yaml")
    with (folder / "agent.log").open("wb") as out:
        agent = subprocess.Popen([*CLI, "agent", "--name", "cam", "--connect", endpoint, "--security", lab],
                                 stdout=out, stderr=subprocess.STDOUT)
    run = subprocess.Popen([*CLI, "run", str(folder / "g.yaml"), "--connect", endpoint, "--security", lab],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        command_lines = []
        seen = threading.Event()

        def scan() -> None:  # while the nodes run: no password on any process's command line
            while not seen.is_set() and run.poll() is None:
                for proc in Path("/proc").glob("[0-9]*/cmdline"):
                    try:
                        text = proc.read_bytes().decode(errors="replace")
                    except OSError:
                        continue
                    if "mocapflow.runtime.worker" in text and '"prefix":"mocapflow/secured"' in text:
                        command_lines.append(text)
                if len(command_lines) >= 2:
                    seen.set()
                time.sleep(0.05)

        scanner = threading.Thread(target=scan)
        scanner.start()
        out, _ = run.communicate(timeout=60)
        seen.set()
        scanner.join()
    finally:
        for proc in (run, agent):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                proc.wait(timeout=30)
    assert run.returncode == 0, out + (folder / "agent.log").read_text()
    assert "all nodes finished" in out
    assert command_lines and all(lab in c and all(p not in c for p in PASSWORDS.values()) for c in command_lines)
    positions = read_markers(folder / "out.c3d").positions
    assert positions.shape[0] == frames and not np.isnan(positions).any()


@pytest.mark.integration
def test_the_documented_viewer_role_can_neither_deploy_stop_nor_end_a_stream(secured: tuple[str, Path]) -> None:
    """The read-only role of the documented rules, against a live agent: a deployment of a recorder writing a file
    of the viewer's choosing is never delivered, nor is a stop, nor an end of stream; the lab user reaches both."""
    from mocapflow.runtime.keys import deploy_key, stop_key
    from mocapflow.runtime.protocol import Deployment, Placement
    from mocapflow.runtime.worker import WorkerSpec

    endpoint, folder = secured
    with (folder / "agent.log").open("wb") as out:
        agent = subprocess.Popen([*CLI, "agent", "--name", "cam", "--connect", endpoint, "--security",
                                  str(folder / "lab.yaml")], stdout=out, stderr=subprocess.STDOUT)
    chosen = folder / "chosen-by-the-viewer.c3d"
    deployment = Deployment(run="evil", prefix="mocapflow/evil", nodes=[Placement(source=False, spec=WorkerSpec(
        node="recorder", plugin="recorder", config={"path": str(chosen)}, prefix="mocapflow/evil",
        inputs={"markers": "mocapflow/evil/tracker/markers"}))]).model_dump_json()
    viewer, lab = try_open(endpoint, folder / "viewer.yaml"), try_open(endpoint, folder / "lab.yaml")
    assert viewer and lab
    try:
        deadline = time.monotonic() + 30
        while not list(lab.liveliness().get("mocapflow/_agents/cam", timeout=2)):
            assert time.monotonic() < deadline and agent.poll() is None, (folder / "agent.log").read_text()
            time.sleep(0.2)
        assert list(viewer.liveliness().get("mocapflow/_agents/cam", timeout=2))  # the viewer sees the agent
        assert list(viewer.get(deploy_key("cam"), payload=deployment, timeout=3)) == []
        assert list(viewer.get(stop_key("cam"), payload="evil", timeout=3)) == []
        time.sleep(1)
        assert not chosen.with_name(chosen.name + ".part").exists() and "evil" not in (folder / "agent.log").read_text()
        # the queryables are there for the lab user: an invalid deployment is answered with the agent's error
        replies = list(lab.get(deploy_key("cam"), payload=b"{}", timeout=5))
        assert replies and replies[0].err is not None and "invalid deployment" in replies[0].err.payload.to_string()
        # a viewer's end of stream never reaches a subscriber of the data
        ended = []
        with lab.declare_subscriber("mocapflow/t/tracker/markers", lambda s: ended.append(s.kind)), \
                viewer.declare_publisher("mocapflow/t/tracker/markers") as pub:
            time.sleep(0.3)
            pub.delete()
            time.sleep(0.5)
        assert ended == []
    finally:
        viewer.close()
        lab.close()
        agent.send_signal(signal.SIGTERM)
        agent.wait(timeout=30)
