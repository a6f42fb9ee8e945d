"""The process around the command line of :mod:`bftaichi.cli`: :func:`freeze_heap` for its
garbage collections, :func:`quick_exit` to end it as soon as its work is done."""

from __future__ import annotations

import os
import sys

__all__ = ["freeze_heap", "quick_exit"]


def freeze_heap() -> None:
    """Freeze the imports' objects (~140k), so the collections that free Taichi's compiling calls
    scan only the run's (0.09 s -> 2 us each; the ``run`` and ``fuse`` commands). Unfrozen at
    exit: without :func:`quick_exit`, Taichi writes its offline cache when the last collection
    frees its program (tests/test_cli.py)."""
    import atexit
    import gc

    import taichi  # noqa: F401  the largest of the run's imports, loaded lazily otherwise

    from .running import pipeline  # noqa: F401

    gc.freeze()
    atexit.register(gc.unfreeze)


def quick_exit(rc: int) -> None:
    """End the process with exit code ``rc`` once a command is done (:func:`bftaichi.cli.console`).

    What Python and the libraries registered to run at exit runs (``atexit``), Taichi's
    program is released (that writes its offline cache: the next command starts warm), stdout
    and stderr are flushed, and the process ends with ``os._exit``, without the interpreter
    tearing down every module and Taichi's LLVM runtime object by object, which took 0.3-0.4 s
    of a warm default run (docs/measurements.md, "Start-up: what a warm run spends outside the
    model"). Call it only when every file the command writes is complete and closed. Under a
    profiler or a tracer (``python -m cProfile``, coverage, a debugger) it exits the usual way,
    so that they can write what they collected."""
    import atexit

    if sys.getprofile() is not None or sys.gettrace() is not None:
        sys.exit(rc)
    try:
        atexit._run_exitfuncs()
        if "taichi" in sys.modules:
            from . import backend

            if backend.is_initialized():
                import taichi as ti

                ti.reset()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (AttributeError, OSError, ValueError):
                pass  # closed, or a pipe whose reader went away: nothing more to say
        os._exit(rc)
