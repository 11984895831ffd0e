import pytest

import pdvc
from pdvc.projectors import available_backends, get_backend, register_backend
from pdvc.projectors import _registry


def test_cpu_backend_always_available():
    assert "cpu" in available_backends()
    assert get_backend("auto").name == "cpu"
    assert get_backend("cpu") is get_backend("cpu")


def test_unknown_backend_lists_the_registered_ones():
    with pytest.raises(pdvc.BackendError, match="'cpu'"):
        get_backend("gpu-that-does-not-exist")


def test_unavailable_backend_is_skipped_by_auto_but_explicit_name_errors(monkeypatch):
    monkeypatch.setattr(_registry, "_FACTORIES", dict(_registry._FACTORIES))
    monkeypatch.setattr(_registry, "_PREFERENCE", list(_registry._PREFERENCE))
    monkeypatch.setattr(_registry, "_INSTANCES", dict(_registry._INSTANCES))

    def broken():
        raise ImportError("no CUDA here")

    register_backend("fake-gpu", broken, prefer=True)
    assert get_backend("auto").name == "cpu"
    assert "fake-gpu" not in available_backends()
    with pytest.raises(pdvc.BackendError, match="no CUDA here"):
        get_backend("fake-gpu")
