"""TLS in the server itself (``--ssl-certfile`` / ``--ssl-keyfile``): wss:// and https:// on one port, with a
certificate the test makes (trustme); clients trust it through the standard ``SSL_CERT_FILE``."""

from __future__ import annotations

import json
import ssl
import subprocess
import sys
import urllib.request

import pytest
import trustme
from loopback import RECORDINGS, Client, running_server, stream_flowed

from egoposevr.cli.main import main
from egoposevr.protocol import Ping
from egoposevr.server.config import ConfigError, ServerConfig, load_config


@pytest.fixture(scope="module")
def certificate(tmp_path_factory):
    """(CA bundle, certificate chain, key) PEM files for 127.0.0.1 and localhost."""
    folder = tmp_path_factory.mktemp("tls")
    ca = trustme.CA()
    cert = ca.issue_cert("127.0.0.1", "localhost")
    paths = folder / "ca.pem", folder / "server.pem", folder / "server.key"
    ca.cert_pem.write_to_path(str(paths[0]))
    cert.cert_chain_pems[0].write_to_path(str(paths[1]))
    for pem in cert.cert_chain_pems[1:]:
        pem.write_to_path(str(paths[1]), append=True)
    cert.private_key_pem.write_to_path(str(paths[2]))
    return paths


def test_wss_and_https_on_one_port(certificate, monkeypatch, tmp_path):
    ca, chain, key = certificate
    monkeypatch.setenv("SSL_CERT_FILE", str(ca))  # what a user does for a private CA
    with running_server(ssl_certfile=chain, ssl_keyfile=key) as server:
        assert server.url.startswith("wss://127.0.0.1:")
        with Client(server.url, "secure") as client:
            assert client.hello("render", "secure").type == "welcome"
            client.send(Ping(nonce=7))
            assert client.recv_type("pong").nonce == 7
        context = ssl.create_default_context(cafile=str(ca))
        port = server.server.port
        with urllib.request.urlopen(f"https://127.0.0.1:{port}/readyz", context=context, timeout=5) as reply:
            assert reply.status == 200
        report = tmp_path / "report.json"
        walk = str(RECORDINGS / "walk-0000.egrec")
        code = main(["replay", walk, "--url", f"wss://127.0.0.1:{port}", "--model", "hmd", "--seconds", "1",
                     "--json", str(report), "--quiet"])  # fmt: skip
        assert code == 0 and stream_flowed(json.loads(report.read_text()))


def test_plain_ws_to_a_tls_port_does_not_connect(certificate):
    _, chain, key = certificate
    with (
        running_server(ssl_certfile=chain, ssl_keyfile=key) as server,
        pytest.raises(Exception),  # noqa: B017, PT011 - it fails in the HTTP parser or the TLS layer
    ):
        Client(server.url.replace("wss://", "ws://"), "plain")


def test_tls_settings_are_checked_before_anything_binds(certificate, tmp_path):
    _, chain, _ = certificate
    with pytest.raises(ConfigError, match="ssl_keyfile needs ssl_certfile"):
        load_config({"ssl_keyfile": chain})
    with pytest.raises(ConfigError, match="does not exist"):
        load_config({"ssl_certfile": tmp_path / "missing.pem"})
    bad = tmp_path / "bad.pem"
    bad.write_text("not a certificate")
    with pytest.raises(ConfigError, match="cannot load the certificate"):
        ServerConfig(ssl_certfile=bad).ssl_context()
    result = subprocess.run(
        [sys.executable, "-m", "egoposevr.cli.main", "serve", "--port", "0", "--ssl-certfile", str(bad)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode == 2 and "cannot load the certificate" in result.stderr
