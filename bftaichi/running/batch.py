"""``bftaichi batch``: many runs, one Ray task each (issue 20; DESIGN.md section 7).

A manifest lists the runs::

    [[run]]
    scene = "scenes/bunny.toml"           # relative paths resolve against the manifest
    name = "bunny-5mm"                    # optional: the output folder (default: the scene's name)
    set = ["tsdf.voxel_size_m=0.005"]     # optional: --set overrides

Each run is one Ray task (``num_cpus=1``) that runs exactly what ``bftaichi run SCENE --out
DIR/<name>`` runs, so ``mesh.ply`` and ``band.npz`` are byte-identical to a local run. Ray
starts a local cluster of ``workers`` CPUs, or joins a running one at ``address``; a worker
process initialises Taichi once and keeps it for every run it gets (Taichi's offline cache
serves the kernels). A failing run (bad scene, missing data, out of memory) is recorded and the
others go on; a run whose worker process dies is retried once (Ray's ``max_retries``), then
reported. ``DIR/batch.json`` records per run its status, seconds, peak memory, worker and
error, and is rewritten after every run, so an interrupted batch leaves a true record; each
run's own outputs are committed atomically by the pipeline, so Ctrl-C leaves every completed run
intact. ``resume`` skips the runs whose outputs are complete.

A run solved in spatial chunks (``run.chunk_m``) sends each chunk to Ray as a task of its own
(:func:`bftaichi.stages.chunks.ray_chunks`): one large scene spreads over the cluster. A run's
task waits for its chunks without holding its CPU (Ray lends it to the chunks).
"""

from __future__ import annotations

import os
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

from ..errors import BftaichiError, ConfigError

__all__ = ["RunSpec", "read_manifest", "run_batch", "BATCH_FILE"]

BATCH_FILE = "batch.json"
_KEYS = ("name", "scene", "set")


@dataclass(frozen=True)
class RunSpec:
    """One ``[[run]]`` of a manifest: output folder name, scene file (absolute), overrides."""

    name: str
    scene: str
    sets: tuple[str, ...] = ()


def read_manifest(path: str | os.PathLike) -> list[RunSpec]:
    """The runs of a manifest, checked: known keys only, every scene file present, names
    unique and usable as folder names. Raises ConfigError naming the file and the run."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"manifest {path} does not exist")
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: not valid TOML ({e})") from None
    extra = sorted(set(data) - {"run"})
    if extra:
        raise ConfigError(f"{path}: unknown top-level key {extra[0]!r}; a manifest holds only "
                          "[[run]] tables")
    runs = data.get("run")
    if not isinstance(runs, list) or not runs or not all(isinstance(r, dict) for r in runs):
        raise ConfigError(f"{path}: no [[run]] tables")
    specs, seen = [], {}
    for i, r in enumerate(runs, 1):
        where = f"{path}: [[run]] {i}"
        unknown = sorted(set(r) - set(_KEYS))
        if unknown:
            raise ConfigError(f"{where}: unknown key {unknown[0]!r}; known: {', '.join(_KEYS)}")
        if not isinstance(r.get("scene"), str):
            raise ConfigError(f"{where}: needs scene = \"path/to/scene.toml\"")
        scene = (path.parent / r["scene"]).resolve()
        if not scene.is_file():
            raise ConfigError(f"{where}: scene file {scene} does not exist")
        sets = r.get("set", [])
        if not isinstance(sets, list) or not all(isinstance(s, str) for s in sets):
            raise ConfigError(f"{where}: set must be a list of \"section.key=value\" strings")
        name = r.get("name", _scene_name(scene))
        if (not isinstance(name, str) or not name or name in (".", "..")
                or any(c in name for c in "/\\")):
            raise ConfigError(f"{where}: name {name!r} is not a folder name")
        if name in seen:
            raise ConfigError(f"{where}: duplicate name {name!r} (also [[run]] {seen[name]}); "
                              "give each run its own name")
        seen[name] = i
        specs.append(RunSpec(name=name, scene=str(scene), sets=tuple(sets)))
    return specs


def _scene_name(scene: Path) -> str:
    """The ``[scene] name`` of a scene file, else its stem (a broken file fails as a run)."""
    try:
        name = tomllib.loads(scene.read_text()).get("scene", {}).get("name")
    except (tomllib.TOMLDecodeError, UnicodeDecodeError, AttributeError):
        name = None
    return name if isinstance(name, str) and name else scene.stem


def complete(folder: Path) -> bool:
    """True if ``folder`` holds a run that finished: report.json says ``complete`` and the
    meshes and band it lists are there."""
    import json

    try:
        report = json.loads((folder / "report.json").read_text())
    except (OSError, ValueError):
        return False
    need = ["tsdf_mesh.ply", "band.npz"] + (["mesh.ply"] if "posterior" in
                                            report.get("stages_run", []) else [])
    return report.get("status") == "complete" and all((folder / f).is_file() for f in need)


def run_one(name: str, scene: str, sets: tuple[str, ...], out_root: str, cwd: str) -> dict:
    """One run, in whatever process runs it (a Ray worker): ``bftaichi run SCENE --out
    OUT_ROOT/NAME --overwrite``; never raises for a failing run, returns its record."""
    import socket

    t0 = time.perf_counter()
    record = {"name": name, "scene": scene, "worker": f"{socket.gethostname()}:{os.getpid()}"}
    try:
        if os.path.isdir(cwd):  # relative data paths in scene files mean what they do locally
            os.chdir(cwd)
        from .. import backend
        from ..config import load_config
        from ..stages.chunks import ray_chunks
        from .pipeline import run

        cfg = load_config(scene, list(sets))
        backend.init(cfg.run.arch)  # once per worker process: a no-op for its later runs
        with ray_chunks():  # a chunked run (run.chunk_m) sends its chunks to Ray as tasks
            report = run(cfg, Path(out_root) / name, overwrite=True, progress=False)
        peak = (report.get("memory") or {}).get("peak_rss") or {}
        record.update(status="ok", peak_bytes=peak.get("peak"))
    except BftaichiError as e:
        record.update(status="failed", error=str(e))
    except MemoryError:
        record.update(status="failed", error="out of memory")
    except Exception as e:  # noqa: BLE001 - any failure of one run is that run's record
        record.update(status="failed", error=f"{type(e).__name__}: {e}")
    record["seconds"] = round(time.perf_counter() - t0, 3)
    return record


def run_batch(manifest: str | os.PathLike, out: str | os.PathLike, *, workers: int | None = None,
              address: str | None = None, resume: bool = False, progress: bool = True) -> dict:
    """Run every run of ``manifest`` into ``out/<name>`` on Ray; return the batch record
    (what ``out/batch.json`` holds). Ctrl-C cancels the pending runs, records them as
    ``interrupted`` and re-raises."""
    from ..io import ensure_out_dir, write_json

    specs = read_manifest(manifest)
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers = {workers} must be at least 1")
    try:
        import ray
    except ImportError:
        raise BftaichiError("bftaichi batch needs Ray: pip install \"bftaichi[distributed]\" "
                            "(or pip install ray)") from None
    out = ensure_out_dir(out)
    t0 = time.perf_counter()
    record = {"manifest": str(Path(manifest).resolve()), "out": str(out.resolve()),
              "workers": workers or os.cpu_count(), "address": address, "runs": {}}
    todo = []
    for s in specs:
        if resume and complete(out / s.name):
            record["runs"][s.name] = {"name": s.name, "scene": s.scene, "status": "skipped"}
        else:
            record["runs"][s.name] = {"name": s.name, "scene": s.scene, "status": "pending"}
            todo.append(s)

    def save():
        runs = list(record["runs"].values())
        counts = {k: sum(r["status"] == k for r in runs)
                  for k in ("ok", "failed", "skipped", "interrupted", "pending")}
        write_json(out / BATCH_FILE, {**record, "runs": runs, "counts": counts,
                                       "seconds": round(time.perf_counter() - t0, 3)})

    save()
    if not todo:
        return _finish(record, out)
    started = not ray.is_initialized()
    if started:
        kw = {"address": address} if address else {"num_cpus": record["workers"]}
        ray.init(**kw, include_dashboard=False, log_to_driver=False,
                 configure_logging=False)
    task = ray.remote(num_cpus=1, max_retries=1)(run_one)
    refs = {task.remote(s.name, s.scene, s.sets, str(out.resolve()), os.getcwd()): s
            for s in todo}
    pending = list(refs)
    from tqdm import tqdm

    try:
        with tqdm(total=len(todo), desc="batch", unit="run", disable=None if progress else True,
                  leave=False) as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                spec = refs[done[0]]
                try:
                    result = ray.get(done[0])
                except ray.exceptions.RayError as e:  # the worker died twice (retried once)
                    result = {"name": spec.name, "scene": spec.scene, "status": "failed",
                              "error": f"worker process died, retried once: "
                                       f"{type(e).__name__}: {str(e).splitlines()[0]}"}
                record["runs"][spec.name] = result
                save()
                bar.update(1)
    except KeyboardInterrupt:
        for ref in pending:
            ray.cancel(ref, force=True)
            record["runs"][refs[ref].name]["status"] = "interrupted"
        save()
        raise
    finally:
        if started:
            ray.shutdown()
    return _finish(record, out)


def _finish(record: dict, out: Path) -> dict:
    import json

    return json.loads((out / BATCH_FILE).read_text())


def summary_lines(batch: dict) -> list[str]:
    """The table ``bftaichi batch`` prints at the end."""
    rows = [("run", "status", "seconds", "peak MiB", "worker", "error")]
    for r in batch["runs"]:
        peak = r.get("peak_bytes")
        rows.append((r["name"], r["status"], f"{r['seconds']:.1f}" if "seconds" in r else "-",
                     f"{peak / 2 ** 20:.0f}" if peak else "-", r.get("worker", "-"),
                     (r.get("error") or "")[:70]))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in rows]
    c = batch["counts"]
    lines.append(f"{c['ok']} ok, {c['failed']} failed, {c['skipped']} skipped"
                 + (f", {c['interrupted']} interrupted" if c["interrupted"] else "")
                 + f" in {batch['seconds']:.1f} s")
    return lines
