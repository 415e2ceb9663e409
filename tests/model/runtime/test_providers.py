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


def test_cuda_libraries_of_the_nvidia_wheels_are_preloaded_once_and_a_failure_only_warns(monkeypatch, caplog):
    """onnxruntime-gpu finds the pip-installed CUDA / cuDNN only through preload_dlls; without it the CUDA
    provider cannot load them unless they are on LD_LIBRARY_PATH."""
    from egoposevr.model.runtime import loading

    calls = []
    monkeypatch.setattr(loading.ort, "preload_dlls", lambda: calls.append(1), raising=False)
    loading._preload_cuda_libraries.cache_clear()
    loading._preload_cuda_libraries()
    loading._preload_cuda_libraries()
    assert calls == [1]

    def broken() -> None:
        raise OSError("libcudnn.so.9: cannot open shared object file")

    monkeypatch.setattr(loading.ort, "preload_dlls", broken, raising=False)
    loading._preload_cuda_libraries.cache_clear()
    loading._preload_cuda_libraries()  # does not raise
    loading._preload_cuda_libraries.cache_clear()
    assert "libcudnn.so.9" in caplog.text
