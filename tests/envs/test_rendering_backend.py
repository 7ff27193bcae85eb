"""Tests of the headless OpenGL backend selection (sb3_collapse.envs.rendering)."""

from __future__ import annotations

import os
import sys
import types

import pytest

from sb3_collapse.envs import ensure_rendering_backend, rendering
from sb3_collapse.errors import MissingDependencyError


@pytest.fixture
def unset_backend(monkeypatch: pytest.MonkeyPatch) -> None:
    """No MUJOCO_GL and no cached choice; both are restored after the test."""
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    monkeypatch.setattr(rendering, "_chosen_backend", None)
    monkeypatch.setattr(rendering, "_failure_report", None)
    # dm_control is imported by other tests: hide it so that no "imported too early" warning is emitted.
    for module in ("dm_control.mujoco", "dm_control._render"):
        monkeypatch.delitem(sys.modules, module, raising=False)


def fake_check(working: set[str], calls: list[str]):
    """:return: A replacement of ``_backend_works`` where only the ``working`` backends work."""

    def check(backend: str, timeout: float = 60.0) -> tuple[bool, str]:
        calls.append(backend)
        if backend in working:
            return True, ""
        return False, f"{backend}: libEGL.so.1: cannot open shared object file"

    return check


def test_preset_mujoco_gl_is_respected(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    calls: list[str] = []
    monkeypatch.setattr(rendering, "_backend_works", fake_check(set(), calls))
    assert ensure_rendering_backend() == "osmesa"
    assert ensure_rendering_backend(required=False) == "osmesa"
    assert calls == []
    assert os.environ["MUJOCO_GL"] == "osmesa"


@pytest.mark.usefixtures("unset_backend")
def test_no_backend_raises_with_install_instructions(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[str] = []
    monkeypatch.setattr(rendering, "_backend_works", fake_check(set(), calls))
    with pytest.raises(MissingDependencyError) as error:
        ensure_rendering_backend()
    assert isinstance(error.value, ImportError)  # a missing system library
    message = str(error.value)
    assert "No headless OpenGL backend" in message
    assert "libosmesa6" in message
    assert "libegl1" in message
    assert "MUJOCO_GL" in message
    assert "cannot open shared object file" in message  # the checks' stderr
    assert calls == ["egl", "osmesa"]
    assert "MUJOCO_GL" not in os.environ


@pytest.mark.usefixtures("unset_backend")
def test_no_backend_not_required_returns_none(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[str] = []
    monkeypatch.setattr(rendering, "_backend_works", fake_check(set(), calls))
    assert ensure_rendering_backend(required=False) is None
    assert "MUJOCO_GL" not in os.environ
    # The failure is cached: no second probing, but a later required call still raises.
    assert ensure_rendering_backend(required=False) is None
    with pytest.raises(MissingDependencyError, match="libosmesa6"):
        ensure_rendering_backend(required=True)
    assert calls == ["egl", "osmesa"]


@pytest.mark.usefixtures("unset_backend")
def test_first_working_backend_is_exported_and_cached(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[str] = []
    monkeypatch.setattr(rendering, "_backend_works", fake_check({"osmesa"}, calls))
    assert ensure_rendering_backend() == "osmesa"
    assert os.environ["MUJOCO_GL"] == "osmesa"
    assert os.environ["PYOPENGL_PLATFORM"] == "osmesa"
    assert calls == ["egl", "osmesa"]
    # Cached, and re-exported if the variables were removed meanwhile.
    del os.environ["MUJOCO_GL"]
    assert ensure_rendering_backend() == "osmesa"
    assert os.environ["MUJOCO_GL"] == "osmesa"
    assert calls == ["egl", "osmesa"]


@pytest.mark.usefixtures("unset_backend")
def test_warns_if_dm_control_was_imported_first(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "dm_control.mujoco", types.ModuleType("dm_control.mujoco"))
    monkeypatch.setattr(rendering, "_backend_works", fake_check({"egl"}, []))
    with pytest.warns(RuntimeWarning, match=r"Call sb3_collapse.envs.ensure_rendering_backend\(\) before importing"):
        assert ensure_rendering_backend() == "egl"


def test_check_reports_a_broken_backend() -> None:
    works, stderr = rendering._backend_works("not_a_backend")
    assert not works
    assert stderr


@pytest.mark.usefixtures("unset_backend")
def test_real_check_exports_a_headless_backend() -> None:
    backend = ensure_rendering_backend(required=False)
    if backend is None:
        pytest.skip("no headless OpenGL backend on this machine")
    assert backend in rendering.HEADLESS_BACKENDS
    assert os.environ["MUJOCO_GL"] == os.environ["PYOPENGL_PLATFORM"] == backend


@pytest.fixture
def fake_triton(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, int]]:
    """Triton "installed" and not loaded yet in this process: :func:`load_triton_before_mesa` imports a fake that
    records ``(module, dlopen flags)`` in the list returned; no LLVM library loaded unless a test says so."""
    loads: list[tuple[str, int]] = []
    fake_importlib = types.SimpleNamespace(
        util=types.SimpleNamespace(find_spec=lambda name: object() if name == "triton" else None),
        import_module=lambda name: loads.append((name, sys.getdlopenflags())),
    )
    monkeypatch.setattr(rendering, "importlib", fake_importlib)
    monkeypatch.setattr(rendering, "_triton_checked", False)
    monkeypatch.setattr(rendering, "_loaded_llvm_libraries", list)
    monkeypatch.delitem(sys.modules, "triton._C.libtriton", raising=False)
    return loads


def test_triton_is_loaded_once_before_a_preset_backend_is_kept(
    monkeypatch: pytest.MonkeyPatch, fake_triton: list[tuple[str, int]]
) -> None:
    monkeypatch.setenv("MUJOCO_GL", "osmesa")  # as in SubprocVecEnv workers and Ray trials: the early return
    flags = sys.getdlopenflags()
    assert ensure_rendering_backend() == "osmesa"
    assert ensure_rendering_backend() == "osmesa"
    assert fake_triton == [("triton._C.libtriton", flags)]  # once, loaded the ordinary way


@pytest.mark.usefixtures("unset_backend")
def test_triton_is_loaded_before_a_backend_is_chosen(
    monkeypatch: pytest.MonkeyPatch, fake_triton: list[tuple[str, int]]
) -> None:
    calls: list[str] = []

    def check(backend: str, timeout: float = 60.0) -> tuple[bool, str]:
        calls.append(backend)
        assert fake_triton, "the backend was checked before triton was loaded"
        return True, ""

    monkeypatch.setattr(rendering, "_backend_works", check)
    assert ensure_rendering_backend() == "egl"
    assert calls == ["egl"]
    assert [name for name, _ in fake_triton] == ["triton._C.libtriton"]


@pytest.mark.skipif(not hasattr(os, "RTLD_DEEPBIND"), reason="no RTLD_DEEPBIND on this platform")
def test_triton_after_an_llvm_library_is_loaded_with_deepbind_and_a_warning(
    monkeypatch: pytest.MonkeyPatch, fake_triton: list[tuple[str, int]]
) -> None:
    monkeypatch.setattr(rendering, "_loaded_llvm_libraries", lambda: ["libLLVM-15.so.1"])
    flags = sys.getdlopenflags()
    with pytest.warns(RuntimeWarning, match=r"libLLVM-15\.so\.1.*import triton before rendering"):
        rendering.load_triton_before_mesa()
    assert fake_triton == [("triton._C.libtriton", flags | os.RTLD_DEEPBIND)]
    assert sys.getdlopenflags() == flags  # restored


def test_without_triton_nothing_is_loaded(monkeypatch: pytest.MonkeyPatch, fake_triton: list[tuple[str, int]]) -> None:
    monkeypatch.setattr(rendering.importlib.util, "find_spec", lambda name: None)
    monkeypatch.setattr(rendering, "_loaded_llvm_libraries", lambda: pytest.fail("LLVM looked for without triton"))
    rendering.load_triton_before_mesa()
    assert fake_triton == []
