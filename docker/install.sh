#!/bin/sh
# The image's install steps, shared with CI (docker/check-install.sh runs them in a fresh virtual environment,
# since no Docker engine is available there). Installs the serving package only: onnxruntime, no torch.
# Usage: sh docker/install.sh SOURCE_DIR [ONNXRUNTIME_PACKAGE]
# ONNXRUNTIME_PACKAGE (default onnxruntime) replaces the CPU onnxruntime: onnxruntime-gpu for CUDA and
# TensorRT (the GPU image, docker/README.md), onnxruntime-openvino for OpenVINO.
set -eu
src="${1:-.}"
runtime="${2:-onnxruntime}"
python -m pip install --no-cache-dir --disable-pip-version-check --quiet "$src"
if [ "$runtime" != "onnxruntime" ]; then
    python -m pip uninstall --yes --quiet onnxruntime
    python -m pip install --no-cache-dir --disable-pip-version-check --quiet "$runtime"
fi
# The serving image must never carry torch (it is only for training and export).
if python -m pip show torch >/dev/null 2>&1; then
    echo "install.sh: torch got installed; the serving image must not carry it" >&2
    exit 1
fi
python -c "import sys, egoposevr.server.app; assert 'torch' not in sys.modules"
egoposevr models >/dev/null
