"""The one owner of pybullet's EGL renderer in a process: pybullet clients with the EGL plugin loaded.

Three facts of pybullet 3.2.7's EGL plugin (with Mesa or a GPU driver) decide how clients are handled:

- Each client's plugin makes its own EGL context current when it starts and never again, so every later
  GL call of every client lands in the newest context: two live envs drew each other's shapes and one's
  reset blanked the other. Hence the owner records each client's context and makes it current
  (``activate``) whenever a simulator hands out its client id, i.e. before any pybullet call on it.
- Unloading the plugin or disconnecting any EGL client terminates the process-wide EGL display, so
  every other live EGL client's renders come back blank (depth at the near plane everywhere). Hence
  EGL clients are never disconnected while the process lives: a closed ``Simulator`` hands its client
  back here with its world emptied, and the next EGL simulator of the process reuses it.
- EGL does not survive ``fork``: the driver's render threads stay in the parent, so a forked child's
  first render waits for them forever (``AsyncVectorEnv``'s default start method on Linux is fork).
  Hence EGL is touched only at a simulator's first use (constructing an env renders nothing, so the
  throw-away env gymnasium builds in the parent to read the spaces does not start EGL there), and a
  forked child whose parent had already started EGL gets ``EGLForkError`` instead of a hang.

A new EGL client renders a few throw-away frames before it is handed out: the first frames of a fresh
context are shaded differently from all later ones, and images must not depend on whether a client
is fresh or reused.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import importlib.util
import logging
import os
import threading

import pybullet as pb

log = logging.getLogger(__name__)

_WARM_UP_FRAMES = 3  # throw-away renders of a new context (the first two are shaded differently)
_EGL_DRAW, _EGL_READ = 0x3059, 0x305A  # eglGetCurrentSurface's arguments (EGL 1.4 headers)


class EGLForkError(RuntimeError):
    """EGL was started in this process's parent before it forked; it cannot be used here."""


class EGLOwner:
    """Hands out pybullet DIRECT clients with the EGL plugin loaded, and takes them back for reuse."""

    def __init__(self) -> None:
        self._idle: list[tuple[int, int]] = []  # (client, plugin id), world empty
        self._live: dict[int, int] = {}  # client -> plugin id, held by a simulator
        self._started = False  # EGL was initialised in this process (or, once forked, in its parent)
        self._inherited = False  # this process is a fork of one that had started EGL
        self._broken = False  # the plugin cannot be loaded here: cameras use the TinyRenderer
        self._contexts: dict[int, tuple[int, int, int, int]] = {}  # client -> (display, draw, read, context)
        self._current: tuple[int, int] | None = None  # (thread id, client) whose context was made current last

    # ------------------------------------------------------------------ lifecycle
    def acquire(self) -> tuple[int, int]:
        """A connected client and its EGL plugin id (-1 when EGL is unavailable: plain client)."""
        if self._inherited:
            raise EGLForkError(
                "EGL rendering cannot start in a process forked from one that had already rendered with EGL "
                "(the parent's render threads do not exist here, so the first render would hang). Create the "
                "workers with the 'spawn' or 'forkserver' start method (AsyncVectorEnv(..., context='spawn'), "
                "SubprocVecEnv(..., start_method='forkserver')), build them before the parent renders, or use "
                "SimConfig(egl_rendering=False) (TinyRenderer)")
        if self._idle:
            client, plugin = self._idle.pop()
            self.activate(client)
        else:
            client = _connect()
            plugin = self._load_plugin(client)
            if plugin < 0:
                return client, -1
            self._started = True
            self._contexts[client] = _current_context()  # the plugin has just made its new context current
            self._current = (threading.get_ident(), client)
            _warm_up(client)
        self._live[client] = plugin
        return client, plugin

    def activate(self, client: int) -> None:
        """Make ``client``'s EGL context current on this thread (a no-op when it already is)."""
        key = (threading.get_ident(), client)
        if key == self._current:
            return
        display, draw, read, context = self._contexts[client]
        if not _egl().eglMakeCurrent(display, draw, read, context):
            raise RuntimeError(f"eglMakeCurrent failed for pybullet client {client}")
        self._current = key

    def release(self, client: int) -> None:
        """Take back ``client`` from a closing simulator: its world is emptied and the client kept."""
        plugin = self._live.pop(client, None)
        if plugin is None:
            raise ValueError(f"pybullet client {client} is not an EGL client held from this owner")
        self.activate(client)
        pb.resetSimulation(physicsClientId=client)
        self._idle.append((client, plugin))

    def is_live(self, client: int | None) -> bool:
        """Whether ``client`` is an EGL client handed out by this owner and not yet released."""
        return client is not None and client in self._live

    @property
    def started(self) -> bool:
        """Whether EGL has been initialised in this process (then a plain fork cannot render with EGL)."""
        return self._started

    @property
    def num_clients(self) -> tuple[int, int]:
        """(live, idle) EGL clients of this process."""
        return len(self._live), len(self._idle)

    # ------------------------------------------------------------------ internals
    def _load_plugin(self, client: int) -> int:
        if self._broken:
            return -1
        spec = importlib.util.find_spec("eglRenderer")  # pybullet ships it as a top-level extension module
        plugin = -1
        if spec is not None and spec.origin:
            try:
                plugin = pb.loadPlugin(spec.origin, "_eglRendererPlugin", physicsClientId=client)
            except pb.error:
                plugin = -1
        if plugin < 0:
            self._broken = True
            log.warning("pybullet's EGL renderer plugin could not be loaded; cameras will use the TinyRenderer")
        return plugin

    def _after_fork_in_child(self) -> None:
        """The inherited clients' EGL state belongs to the parent: forget them without touching pybullet."""
        self._inherited = self._started
        self._idle.clear()
        self._live.clear()
        self._contexts.clear()
        self._current = None


def _connect() -> int:
    client = pb.connect(pb.DIRECT)
    if client < 0:
        raise RuntimeError("could not start a pybullet DIRECT client")
    return client


_LIBEGL: list[ctypes.CDLL] = []


def _egl() -> ctypes.CDLL:
    """The process's libEGL (the one the plugin loaded), with the prototypes used here."""
    if not _LIBEGL:
        lib = ctypes.CDLL(ctypes.util.find_library("EGL") or "libEGL.so.1")
        for name in ("eglGetCurrentDisplay", "eglGetCurrentContext", "eglGetCurrentSurface"):
            getattr(lib, name).restype = ctypes.c_void_p
        lib.eglGetCurrentSurface.argtypes = [ctypes.c_int]
        lib.eglMakeCurrent.argtypes = [ctypes.c_void_p] * 4
        lib.eglMakeCurrent.restype = ctypes.c_uint
        _LIBEGL.append(lib)
    return _LIBEGL[0]


def _current_context() -> tuple[int, int, int, int]:
    lib = _egl()
    handles = (lib.eglGetCurrentDisplay(), lib.eglGetCurrentSurface(_EGL_DRAW), lib.eglGetCurrentSurface(_EGL_READ),
               lib.eglGetCurrentContext())
    if not all(handles):
        raise RuntimeError("pybullet's EGL plugin left no current EGL context to record")
    return handles


def _warm_up(client: int) -> None:
    view = pb.computeViewMatrix([0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    proj = pb.computeProjectionMatrixFOV(45.0, 1.0, 0.1, 3.0)
    for _ in range(_WARM_UP_FRAMES):
        pb.getCameraImage(16, 16, viewMatrix=view, projectionMatrix=proj, renderer=pb.ER_BULLET_HARDWARE_OPENGL,
                          physicsClientId=client)


EGL_OWNER = EGLOwner()
"""This process's owner; every ``Simulator`` with ``SimConfig.egl_rendering`` gets its client here."""

os.register_at_fork(after_in_child=EGL_OWNER._after_fork_in_child)


def connect_plain() -> int:
    """A pybullet DIRECT client without EGL (disconnecting it never affects EGL clients)."""
    return _connect()
