"""Server addresses as people type them: ``ws://host:port`` reaches ``/ws``; ``http://`` is refused clearly."""

import json

import pytest
from loopback import RECORDINGS, running_server, stream_flowed

from egoposevr.cli.main import main
from egoposevr.clients import server_url, session_url


@pytest.mark.parametrize(
    ("typed", "url"),
    [
        ("ws://host:8765", "ws://host:8765/ws"),
        ("ws://host:8765/", "ws://host:8765/ws"),
        ("wss://host/ws", "wss://host/ws"),
        (" ws://host:1/custom?x=1 ", "ws://host:1/custom?x=1"),
    ],
)
def test_urls_are_completed(typed, url):
    assert server_url(typed) == url


@pytest.mark.parametrize(
    ("typed", "hint"),
    [
        ("http://host:8765", "use ws://host:8765/ws"),
        ("https://h/ws", "use wss://h/ws"),
        ("host:8765", "ws://"),
    ],
)
def test_http_and_bare_addresses_are_refused_with_the_scheme_to_use(typed, hint):
    with pytest.raises(ValueError, match=hint):
        server_url(typed)


def test_session_names_are_quoted():
    assert session_url("ws://h:1", "a b") == "ws://h:1/ws?session=a%20b"


def test_a_url_without_a_path_reaches_the_server(tmp_path, capsys):
    report = tmp_path / "report.json"
    with running_server() as server:
        port = server.server.port
        bare = f"ws://127.0.0.1:{port}"
        walk = str(RECORDINGS / "walk-0000.egrec")
        code = main(["replay", walk, "--url", bare, "--model", "hmd", "--seconds", "1", "--json", str(report), "--quiet"])  # fmt: skip
    assert code == 0 and stream_flowed(json.loads(report.read_text()))
    with pytest.raises(SystemExit) as exit_info:
        main(["replay", walk, "--url", f"http://127.0.0.1:{port}"])
    assert exit_info.value.code == 2
    assert "speaks WebSocket, not HTTP; use ws://127.0.0.1" in capsys.readouterr().err
