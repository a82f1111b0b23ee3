"""MuJoCo's offscreen OpenGL backend, chosen before ``mujoco`` is imported.

Without a display MuJoCo renders through EGL (a GPU driver, or Mesa's ``libegl-mesa0``) or
OSMesa (Mesa's CPU renderer: ``apt-get install libosmesa6`` on Debian/Ubuntu). It reads
``MUJOCO_GL`` once, when it is imported, so a program that renders calls
:func:`choose_gl_backend` first. This module imports nothing that imports MuJoCo.
"""

from __future__ import annotations

import os
import subprocess
import sys

__all__ = ["GL_BACKENDS", "INSTALL_HINT", "RenderBackendError", "choose_gl_backend"]

#: The offscreen backends tried, in order.
GL_BACKENDS: tuple[str, ...] = ("egl", "osmesa")

#: What to install when no backend renders (Debian/Ubuntu).
INSTALL_HINT = (
    "install an offscreen OpenGL: `apt-get install libosmesa6` (OSMesa, CPU) or "
    "`apt-get install libegl1 libegl-mesa0` (EGL; with an NVIDIA driver EGL uses the GPU), "
    "or set MUJOCO_GL to a backend that works here"
)

_PROBE = (
    "import mujoco\n"
    "m = mujoco.MjModel.from_xml_string("
    "'<mujoco><worldbody><geom size=\"0.1\"/></worldbody></mujoco>')\n"
    "with mujoco.Renderer(m, 16, 16) as r:\n"
    "    r.update_scene(mujoco.MjData(m))\n"
    "    assert r.render().shape == (16, 16, 3)\n"
)


class RenderBackendError(RuntimeError):
    """No offscreen OpenGL backend of MuJoCo works on this machine.

    Examples:
        >>> from torchrl_mbmf.offscreen import RenderBackendError
        >>> issubclass(RenderBackendError, RuntimeError)
        True
    """


def _probe(backend: str, timeout: float) -> str | None:
    """``None`` if MuJoCo renders a frame with ``backend`` in a fresh process, else the error."""
    env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        return f"no frame within {timeout:.0f} s"
    if proc.returncode == 0:
        return None
    lines = [line for line in proc.stderr.strip().splitlines() if line.strip()]
    return lines[-1] if lines else f"exit status {proc.returncode}"


def choose_gl_backend(
    candidates: tuple[str, ...] = GL_BACKENDS, *, timeout: float = 60.0, set_env: bool = True
) -> str:
    """MuJoCo's offscreen backend: ``MUJOCO_GL`` if set, else the first candidate that renders.

    Call it before anything imports ``mujoco`` in this process (the backend is read at import).

    Args:
        candidates: backends to try, in order. Defaults to :data:`GL_BACKENDS`.

    Keyword Args:
        timeout: seconds each probe may take. Defaults to ``60``.
        set_env: write the choice to ``MUJOCO_GL`` (and ``PYOPENGL_PLATFORM``). Defaults to
            ``True``.

    Returns:
        The backend's name.

    Raises:
        RenderBackendError: none of the candidates renders; the message gives each one's error
            and what to install.

    Examples:
        >>> import os
        >>> from torchrl_mbmf.offscreen import choose_gl_backend
        >>> os.environ.get("MUJOCO_GL") is None or choose_gl_backend() == os.environ["MUJOCO_GL"]
        True
    """
    chosen = os.environ.get("MUJOCO_GL")
    if chosen:
        return chosen
    if not candidates:
        raise ValueError("candidates must name at least one backend, got ()")
    errors = {}
    for backend in candidates:
        error = _probe(backend, timeout)
        if error is None:
            if set_env:
                os.environ["MUJOCO_GL"] = backend
                os.environ.setdefault("PYOPENGL_PLATFORM", backend)
            return backend
        errors[backend] = error
    tried = "; ".join(f"MUJOCO_GL={b}: {e}" for b, e in errors.items())
    raise RenderBackendError(f"MuJoCo cannot render offscreen here ({tried}); {INSTALL_HINT}")
