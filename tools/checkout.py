"""The tools measure the checkout they live in.

``python tools/X.py`` puts ``tools/`` on ``sys.path``, not the repository root, so a plain
``import bftaichi`` finds whichever bftaichi is installed. With an editable install of another
clone (the usual way to compare a change against a worktree of the commit before it), both
sides of a before/after comparison would then measure the same code. Every tool imports this
module before bftaichi::

    import checkout  # noqa: F401  (this checkout's bftaichi and kernels first on sys.path)

and starts child processes with :func:`child_env`, so they import this checkout too.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def child_env(env: dict | None = None) -> dict:
    """``env`` (default: this process's environment) with this checkout first on
    ``PYTHONPATH``: a child Python (``python -m bftaichi.cli``, ``python -c``) imports it.

    ``PYTHONSAFEPATH=1`` (Python 3.11) keeps the child from putting its working directory
    first on ``sys.path``, ahead of ``PYTHONPATH``: run from another checkout (``python
    ../before/tools/bench_pipeline.py`` in the main one), ``python -m bftaichi.cli`` would
    otherwise import the working directory's bftaichi, and both sides of the comparison would
    measure it (tests/test_layout.py)."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), str(ROOT / "tools"),
                                                    env.get("PYTHONPATH", "")) if p)
    env["PYTHONSAFEPATH"] = "1"  # (nor the script's directory: tools/ is on PYTHONPATH instead)
    return env
