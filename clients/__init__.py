"""Clients of the EgoPoseVR server: mock headset, input library, renderer, VMC bridge, bench. No torch here."""


def session_url(url: str, session: str) -> str:
    """The WebSocket URL with ``?session=`` added (PROTOCOL.md §1: balancers route on it)."""
    return f"{url}{'&' if '?' in url else '?'}session={session}"
