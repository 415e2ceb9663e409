"""Clients of the EgoPoseVR server: the mock headset (replay). No torch here."""
