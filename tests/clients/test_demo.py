"""`egoposevr demo` (what `make demo` runs): server + looping mock headset, a live line, a clean stop."""

from egoposevr.cli.main import main


def test_demo_serves_replays_and_stops(capsys):
    assert main(["demo", "--port", "0", "--seconds", "2", "--model", "hmd"]) == 0
    out = capsys.readouterr().out
    assert "ws://127.0.0.1:" in out and "session 'demo'" in out and "/viewer/?session=demo" in out
    final = next(line for line in out.splitlines() if line.startswith("final: "))
    assert "latency p50" in final and "MPJPE upper" in final and "answered 0 " not in final


def test_demo_refuses_an_unknown_recording(capsys):
    assert main(["demo", "--port", "0", "--recording", "nope"]) == 2
    assert "no bundled recording 'nope'" in capsys.readouterr().err
