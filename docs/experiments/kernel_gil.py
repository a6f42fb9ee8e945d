#!/usr/bin/env python
"""Does a Python thread run while a Taichi kernel runs? (issue 16; docs/measurements.md,
"Taichi kernels hold the GIL")

A thread counts in a tight Python loop, first for 0.5 s while the main thread sleeps, then
while the main thread runs one CPU kernel of about half a second. Taichi 1.7's binding calls a
kernel without releasing the GIL, so the thread barely moves during the kernel: Python work of
other threads (a frame reader's file handling and array conversions, the run's metrics) waits
for each kernel to end::

    python docs/experiments/kernel_gil.py
"""

import threading
import time

import numpy as np
import taichi as ti


@ti.kernel
def busy(a: ti.types.ndarray(dtype=ti.f64, ndim=1), n: ti.i32):
    for i in range(a.shape[0]):
        s = 0.0
        for j in range(n):
            s += ti.sin(s + j)
        a[i] = s


def main() -> None:
    ti.init(arch=ti.cpu)
    a = np.zeros(1000)
    busy(a, 10)  # compiled before anything is timed
    count, stop = [0], [False]

    def spin():
        while not stop[0]:
            count[0] += 1

    thread = threading.Thread(target=spin)
    thread.start()
    time.sleep(0.2)
    c0 = count[0]
    time.sleep(0.5)
    idle = count[0] - c0
    c0, t0 = count[0], time.perf_counter()
    busy(a, 100000)
    seconds, during = time.perf_counter() - t0, count[0] - c0
    stop[0] = True
    thread.join()
    print(f"the thread counted {idle:,} in 0.5 s beside a sleeping main thread, {during:,} during "
          f"a {seconds:.2f} s kernel ({during / seconds / (idle / 0.5):.1%} of its idle rate)")


if __name__ == "__main__":
    main()
