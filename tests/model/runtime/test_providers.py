"""Execution providers: names people type, fallback only where the user listed one, clear refusals."""

import subprocess
import sys

import pytest

from egoposevr.model.runtime.loading import LoadedModel, ProviderError, resolve_providers
from egoposevr.model.weights import model_files

CPU_ONLY = ["CPUExecutionProvider"]


def test_short_and_full_names_resolve_in_preference_order():
    assert resolve_providers("cpu", CPU_ONLY) == ("CPUExecutionProvider",)
    assert resolve_providers(" CUDA , cpu", ["CUDAExecutionProvider", "CPUExecutionProvider"]) == (
        "CUDAExecutionProvider", "CPUExecutionProvider",
    )  # fmt: skip
    assert resolve_providers("CPUExecutionProvider", CPU_ONLY) == ("CPUExecutionProvider",)


def test_a_missing_provider_falls_back_only_to_one_the_user_listed():
    assert resolve_providers("cuda,cpu", CPU_ONLY) == ("CPUExecutionProvider",)
    with pytest.raises(
        ProviderError, match=r"CUDAExecutionProvider is not available.*onnxruntime-gpu.*cuda,cpu"
    ):
        resolve_providers("cuda", CPU_ONLY)
    with pytest.raises(ProviderError, match="TensorrtExecutionProvider"):
        resolve_providers("cpu,tensorrt", CPU_ONLY)  # the last one listed must be there


def test_unknown_and_empty_specs_are_refused():
    with pytest.raises(ProviderError, match="unknown execution provider 'gpu'"):
        resolve_providers("gpu", CPU_ONLY)
    with pytest.raises(ProviderError, match="no execution provider"):
        resolve_providers(" , ", CPU_ONLY)


def test_a_loaded_model_says_which_provider_runs_it():
    model = LoadedModel.load(model_files()["hmd"], providers=("CPUExecutionProvider",))
    assert model.provider == "CPUExecutionProvider"


@pytest.mark.parametrize("command", [["serve"], ["eval", "--data", "nowhere"], ["bench"]])
def test_commands_refuse_an_uninstalled_provider_before_doing_anything(command):
    done = subprocess.run(
        [sys.executable, "-m", "egoposevr.cli.main", *command, "--providers", "tensorrt"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2 and "TensorrtExecutionProvider is not available" in done.stderr
