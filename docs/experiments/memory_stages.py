"""Where a fuse's resident memory goes, sub-stage by sub-stage of the posterior (issue 16;
docs/measurements.md, "Where the 1 cm fuse's memory goes").

Runs ``bftaichi`` in this process with every sub-stage of ``Reconstructor.solve`` (band, noise
fit, observations, prior, MAP, bias, variance, misfit: :class:`bftaichi.stages.bandsolve.Lap`)
reporting, when it ends, the highest resident set size reached inside it (``VmHWM``, reset at
each sub-stage's start), the resident size then, the numpy memory ``tracemalloc`` sees then and
its peak inside the sub-stage. The gap between the two is Taichi's own memory, the libraries'
and the arrays allocated with ``mmap`` (:func:`kernels.stencil.zeros_aligned`), which
``tracemalloc`` does not see. The run's own report.json ``memory.peak_rss`` is not valid for
the posterior stage here (its peak counter is reset at every sub-stage)::

    python docs/experiments/memory_stages.py fuse ../shared/data/rgbd/7scenes-redkitchen --voxel 0.01 --out /tmp/m1 --overwrite

Linux only (``/proc/self/status``, ``/proc/self/clear_refs``).
"""
import sys
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def main(argv) -> int:
    tracemalloc.start(1)
    from bftaichi.cli import main as cli
    from bftaichi.running.resources import PeakRSS, _status_kib
    from bftaichi.stages import bandsolve

    lap = bandsolve.Lap.__call__
    mib = 2.0 ** 20

    def timed(self, name):
        now, peak = tracemalloc.get_traced_memory()
        st = _status_kib(("VmHWM", "VmRSS"))
        lap(self, name)
        print(f"{name:10s} resident peak {st['VmHWM'] / mib:6.0f} MiB, at its end "
              f"{st['VmRSS'] / mib:6.0f}; numpy peak {peak / mib:6.0f}, at its end "
              f"{now / mib:6.0f}", flush=True)
        PeakRSS._reset()  # the kernel's peak counter to the current resident size
        tracemalloc.reset_peak()

    bandsolve.Lap.__call__ = timed
    return cli(argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
