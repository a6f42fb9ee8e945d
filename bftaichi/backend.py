"""The one place that initialises Taichi.

Nothing in bftaichi or kernels calls ``ti.init`` at import time. Library users call
:func:`bftaichi.init` (or let :class:`~bftaichi.stages.integrate.TSDFVolume` call it with the defaults);
embedders that already called ``ti.init`` themselves keep their runtime: :func:`init` only
initialises when Taichi is not running yet, or when a different arch is asked for explicitly.

Compiled kernels are kept in Taichi's offline cache (``~/.cache/taichi`` unless
``TI_OFFLINE_CACHE_FILE_PATH`` is set), so the second run of a command does not recompile.
"""

from __future__ import annotations

import contextlib
import os
import sys
import weakref

from .errors import BftaichiError

__all__ = ["init", "is_initialized", "current_arch", "effective_arch"]

_ARCHES = ("cpu", "cuda", "vulkan", "metal", "gpu")
_GPU_ARCHES = ("cuda", "vulkan", "metal")
"""What ``gpu`` tries, in order. Not Taichi's own ``ti.gpu`` list: it also probes OpenGL, and
that probe crashes the process (segmentation fault) on a machine without a display."""
_state: dict[str, str | None] = {"arch": None, "effective": None}


def init(arch: str = "cpu", *, debug: bool = False, offline_cache: bool = True,
         num_threads: int | None = None) -> None:
    """Initialise the Taichi runtime once.

    Args:
        arch: ``cpu`` (default), ``cuda``, ``vulkan``, ``metal`` or ``gpu`` (any available GPU).
        debug: Taichi debug mode (bounds checks; slow).
        offline_cache: keep compiled kernels on disk across runs (recommended).
        num_threads: CPU threads (default: all cores).

    Taichi falls back to the CPU when the requested GPU backend is unavailable (with a warning
    of its own on stderr): :func:`effective_arch` says what runs.

    Calling it again with the same arch, or with the arch that runs, is a no-op, and so is a
    GPU arch none of whose backends is available while Taichi runs on the CPU (it would fall
    back to the CPU it runs on). A different arch resets Taichi, which invalidates every field
    allocated before: do it before creating volumes.
    """
    if arch not in _ARCHES:
        raise BftaichiError(f"unknown arch {arch!r}; choose one of {', '.join(_ARCHES)}")
    if arch in (_state["arch"], _state["effective"]):
        return
    # No network at run time: Taichi otherwise phones home for a version check.
    os.environ["TI_SKIP_VERSION_CHECK"] = "ON"
    import taichi as ti

    names = _GPU_ARCHES if arch == "gpu" else (arch,)
    wanted = [getattr(ti, a) for a in names] if arch == "gpu" else getattr(ti, arch)
    if _state["effective"] == "cpu" and not any(
            ti.lang.misc.is_arch_supported(getattr(ti, a)) for a in names):
        _state["arch"] = arch  # the fallback Taichi would take: keep its fields alive
        return
    kwargs = dict(arch=wanted, offline_cache=offline_cache, debug=debug,
                  default_fp=ti.f32, default_ip=ti.i32, random_seed=0, log_level=ti.WARN,
                  advanced_optimization=_advanced_optimization())
    if num_threads is not None:
        kwargs["cpu_max_num_threads"] = int(num_threads)
    _lean_source_positions()
    _remembered_source_lines()
    if os.environ.get("BFTAICHI_TAICHI_LAUNCH", "") != "taichi":
        from kernels.launch import install

        install()  # kernels called with numpy arrays launch without Taichi's per-call checks
    with _stdout_to_stderr():  # Taichi prints "[Taichi] Starting on arch=..." on stdout
        ti.init(**kwargs)
    _state["arch"] = arch
    ran = ti.lang.impl.current_cfg().arch
    _state["effective"] = "cpu" if ran in (ti.x64, ti.arm64) else ran.name


def _advanced_optimization() -> bool:
    """Whether Taichi runs its own advanced IR optimisations before LLVM's: off, unless
    ``BFTAICHI_TAICHI_OPT=full``.

    LLVM optimises the generated code either way. Taichi's extra passes cost a cold run of the
    default scene ~4 s of its ~8 s of compilation (the observation kernel 2.2 -> 0.6 s) and
    bought no run time on real frames (docs/measurements.md, "Cold start: Taichi's advanced
    passes off"). The results differ in float rounding only (the mean by at most ~1e-5 voxel);
    the same setting gives the same bytes, run after run."""
    return os.environ.get("BFTAICHI_TAICHI_OPT", "") == "full"


_FROZEN_FILES = ("<frozen importlib._bootstrap>", "<frozen importlib._bootstrap_external>")
"""The file names of the import machinery's frames (:func:`_skip_frozen_frame_scans`)."""


def _skip_frozen_frame_scans() -> None:
    """Let :func:`inspect.getmodule` answer for the import machinery's frames at once.

    Taichi 1.7's ``@ti.func`` decorator asks :func:`inspect.getframeinfo` whether it is used
    inside a class, on the frame three levels up. For a function at a module's top level,
    defined while the module is imported, that is a frame of the frozen
    ``<frozen importlib._bootstrap>``, which has no source file, so :func:`inspect.getmodule`
    scans every module in ``sys.modules`` (twice per decorator) and finds none. Hundreds of
    decorators run when Taichi and the kernels are imported, each scan ~1,600 modules: ~0.3 s
    of each process's start (docs/experiments/frozen_frame_scans.py). Mapping those names to
    no module in :mod:`inspect`'s file cache gives the same answer (none) without the scan.
    ``import bftaichi`` calls it, before Taichi is imported."""
    import inspect

    cache = getattr(inspect, "modulesbyfile", None)
    if isinstance(cache, dict):
        for name in _FROZEN_FILES:
            cache.setdefault(name, "")  # sys.modules has no "": getmodule returns None


def _lean_source_positions() -> None:
    """Make Taichi's front end label each AST node with its file, line and source line only.

    Taichi 1.7 builds, for every node of every kernel it materialises (also when the offline
    cache then serves the compiled code), a message with the node's source excerpt wrapped
    by ``textwrap`` and a caret line under it, for compile errors that may never happen: 1-2 s
    of a warm ``bftaichi run`` (tools/bench_startup.py, docs/measurements.md). The lean label
    keeps what a compile error needs to point at the code (file, line, the line itself); set
    ``BFTAICHI_TAICHI_POSITIONS=full`` for Taichi's own. Applied only where Taichi's
    ``ASTTransformerContext.get_pos_info`` exists as in 1.7."""
    if os.environ.get("BFTAICHI_TAICHI_POSITIONS", "") == "full":
        return
    try:
        from taichi.lang.ast.ast_transformer_utils import ASTTransformerContext as Ctx
    except ImportError:
        return
    if not callable(getattr(Ctx, "get_pos_info", None)) or getattr(Ctx, "_bftaichi_lean", False):
        return

    def get_pos_info(self, node):
        line = node.lineno + self.lineno_offset
        src = self.src[node.lineno - 1] if 0 < node.lineno <= len(self.src) else ""
        return f'File "{self.file}", line {line}, in {self.func.func.__name__}:\n{src}\n'

    Ctx.get_pos_info = get_pos_info
    Ctx._bftaichi_lean = True


def _remembered_source_lines() -> None:
    """Read each Taichi function's source once per process.

    Taichi 1.7's front end reads a function's source lines (``inspect.getsourcelines``, which
    tokenises the file's lines from the function's first) every time it builds a kernel that
    calls the function: 471 reads of 86 functions in a warm ``bftaichi run``, 0.21-0.24 s
    (``python docs/experiments/frozen_frame_scans.py --reads --undo``; 0.08-0.09 s with this).
    The lines of a function object do not change while it lives, so they are kept by function.
    Applied only where ``taichi.lang.kernel_impl.getsourcelines`` exists as in 1.7."""
    try:
        from taichi.lang import kernel_impl
    except ImportError:
        return
    read = getattr(kernel_impl, "getsourcelines", None)
    if not callable(read) or getattr(read, "_bftaichi_remembered", False):
        return
    lines = weakref.WeakKeyDictionary()

    def getsourcelines(func):
        try:
            return lines[func]
        except (KeyError, TypeError):  # not read yet, or an object that takes no weak reference
            pass
        found = read(func)
        try:
            lines[func] = found
        except TypeError:
            pass
        return found

    getsourcelines._bftaichi_remembered = True
    kernel_impl.getsourcelines = getsourcelines


@contextlib.contextmanager
def _stdout_to_stderr():
    """Send what is printed on stdout (by Python or by Taichi's C++ runtime) to stderr: a
    command's stdout carries its results only (``-q``: nothing), and an unwritable stdout
    does not stop the start-up."""
    try:
        sys.stdout.flush()
    except (AttributeError, OSError, ValueError):
        pass
    try:
        saved = os.dup(1)
        os.dup2(2, 1)
    except OSError:  # no file descriptor 1 or 2: the Python-level redirect still holds
        saved = None
    try:
        with contextlib.redirect_stdout(sys.stderr):
            yield
    finally:
        if saved is not None:
            os.dup2(saved, 1)
            os.close(saved)


def is_initialized() -> bool:
    """True once :func:`init` ran in this process."""
    return _state["arch"] is not None


def current_arch() -> str | None:
    """The arch :func:`init` was last asked for (None before it ran)."""
    return _state["arch"]


def effective_arch() -> str | None:
    """The backend Taichi runs on: ``cpu``, ``cuda``, ``vulkan`` or ``metal`` (None before
    :func:`init`); ``cpu`` after a fallback from an unavailable GPU backend."""
    return _state["effective"]
