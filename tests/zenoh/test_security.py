"""TLS with mutual authentication and access control, using the configs of docs/zenoh.md verbatim
(paths and addresses substituted): a throwaway CA and certificates made with the openssl CLI."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from fisc_agent.zenoh.keys import Keys
from fisc_agent.zenoh.link import AgentZenohLink
from fisc_ground.zenoh.fleet import TelemetryListener
from fisc_ground.zenoh.publish import MapServer

from .conftest import free_port, snap, wait_for, zenoh

DOC = Path(__file__).resolve().parents[2] / "docs" / "zenoh.md"
pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI")


def doc_config(name: str) -> str:
    m = re.search(rf"<!-- config: {name} -->\s*```json5\n(.*?)```", DOC.read_text(), re.S)
    assert m, f"docs/zenoh.md has no config block {name!r}"
    return m.group(1)


def openssl(*args, cwd):
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    d = tmp_path_factory.mktemp("pki")
    openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-days", "2",
            "-keyout", "ca.key", "-out", "ca.pem", "-subj", "/CN=fisc-test-ca", cwd=d)
    (d / "ext.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
                               "extendedKeyUsage=serverAuth,clientAuth\n")
    for name in ("router", "fisc-ground", "agent-1", "agent-2"):
        openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-keyout", f"{name}.key",
                "-out", f"{name}.csr", "-subj", f"/CN={name}", cwd=d)
        openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
                "-days", "2", "-extfile", "ext.cnf", "-out", f"{name}.pem", cwd=d)
    return d


@pytest.fixture()
def tls_net(pki, tmp_path):
    port = free_port()

    def write(block: str, who: str | None = None) -> Path:
        text = doc_config(block).replace("/etc/fisc/tls/", f"{pki}/").replace("ground.example:7447",
                                                                               f"127.0.0.1:{port}")
        if who:
            text = text.replace("agent-1", who)
        path = tmp_path / f"{who or block}.json5"
        path.write_text(text)
        return path
    return {"router": write("router-mtls"), "ground": write("agent-1-mtls", "fisc-ground"),
            "agent-1": write("agent-1-mtls"), "agent-2": write("agent-1-mtls", "agent-2"), "port": port}


def test_documented_lab_configs_are_the_ones_the_code_builds():
    from fisc_agent.zenoh.lab_door import door_config_json
    from fisc_agent.zenoh.session import LabDiscovery, lab_config_json

    lab = LabDiscovery()
    for block, built in (("lab-session", lab_config_json(lab)), ("lab-door", door_config_json(lab.endpoint))):
        cfg = zenoh.Config.from_json5(doc_config(block))
        built = zenoh.Config.from_json5(json.dumps(built))
        for key in ("mode", "listen", "connect", "scouting"):
            assert json.loads(cfg.get_json(key)) == json.loads(built.get_json(key)), (block, key)


def test_mtls_and_access_control_as_documented(tls_net, sessions, make_map, ground_key, pki):
    router = sessions(tls_net["router"])
    ground = sessions(tls_net["ground"])
    server = MapServer(ground, "alpha", announce_period_s=0.2)
    served = server.serve(make_map(100))
    listener = TelemetryListener(ground, Keys("fisc", "alpha"))
    links = {}
    try:
        for i in (1, 2):
            links[i] = AgentZenohLink(tls_net[f"agent-{i}"], "alpha", i, [ground_key[1]], False,
                                      lambda m: None, lambda c: None).start()
            links[i].start_telemetry(lambda: snap(), rate_hz=20)
        assert wait_for(lambda: all(l.current is not None for l in links.values()))
        assert links[1].current.sha256 == served.sha256
        assert wait_for(lambda: set(listener.snapshot()) == {1, 2})
        # the router saw the agents' certificate names
        assert {"agent-1", "agent-2"} <= {link.auth_identifier for link in router.info.links()}

        # agent 1 posing as agent 2, and agent 1 publishing a command: dropped by the router.
        # Positive control: agent 1's puts on its OWN telemetry key, interleaved on the same
        # session and route, do arrive; once the last of them is in, a forged message sent
        # before it would have arrived too (one session, one route, in order).
        forged, cmds, control = [], [], []
        cmd_sub = ground.declare_subscriber("fisc/alpha/cmd", lambda s: cmds.append(s))
        spy = ground.declare_subscriber("fisc/alpha/agents/2/telemetry",
                                        lambda s: forged.append(s) if s.payload.to_bytes() == b"forged" else None)
        ctl = ground.declare_subscriber("fisc/alpha/agents/1/telemetry",
                                        lambda s: control.append(s) if s.payload.to_bytes() == b"control" else None)
        a1 = links[1]._session  # noqa: SLF001
        # wait until a control put gets through (routes established), then run the rounds
        assert wait_for(lambda: (a1.put("fisc/alpha/agents/1/telemetry", b"control"), len(control) > 0)[1], 10)
        before = len(control)
        for _ in range(5):
            a1.put("fisc/alpha/agents/2/telemetry", b"forged")
            a1.put("fisc/alpha/cmd", b"agent command")
            a1.put("fisc/alpha/agents/1/telemetry", b"control")
        assert wait_for(lambda: len(control) >= before + 5, 10), "the positive control never arrived"
        assert forged == [] and cmds == []
        for sub in (spy, ctl, cmd_sub):
            sub.undeclare()
    finally:
        for link in links.values():
            link.close()
        listener.close()
        server.close()


def test_client_without_a_certificate_is_refused(tls_net, sessions, pki):
    text = tls_net["agent-1"].read_text()
    text = re.sub(r"connect_private_key.*\n|connect_certificate.*\n", "", text)
    path = tls_net["agent-1"].with_name("nocert.json5")
    path.write_text(text)
    sessions(tls_net["router"])
    with pytest.raises(zenoh.ZError, match="Unable to connect"):  # the TLS handshake is refused
        sessions(path)
