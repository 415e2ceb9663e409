"""Torch networks and their torch-side helpers (training and export only; never imported by serving code)."""
