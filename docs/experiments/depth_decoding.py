"""Decoding depth PNGs, and keeping decoded frames compressed in memory instead (issue 16;
measured, not built: docs/measurements.md, "Speed measurements that found nothing to build").

1. Milliseconds a frame to decode ``--frames`` redkitchen depth PNGs held in memory, by
   Pillow (the project's reader) and, where installed, ``imagecodecs`` (libpng, libspng) and
   OpenCV, each checked against Pillow's pixels.
2. The same frames as the reader returns them, kept as millimetre uint16 (or float32)
   through the standard library's ``zlib``: KB a frame and milliseconds to compress and to
   decompress::

    python docs/experiments/depth_decoding.py
"""
import argparse
import io
import sys
import time
import zlib
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="?", type=Path, default=DATA)
    ap.add_argument("--frames", type=int, default=60)
    args = ap.parse_args()
    from PIL import Image

    import bftaichi as bf

    files = sorted(args.data.glob("*.depth.png"))[:args.frames]
    blobs = [f.read_bytes() for f in files]

    def pillow(b):
        with Image.open(io.BytesIO(b)) as im:
            im.load()
            return np.array(im)

    decoders = {"Pillow": pillow}
    try:
        import imagecodecs
        decoders["imagecodecs png"] = imagecodecs.png_decode
        decoders["imagecodecs spng"] = imagecodecs.spng_decode
    except ImportError:
        print("imagecodecs not installed")
    try:
        import cv2
        decoders["OpenCV"] = lambda b: cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_UNCHANGED)
    except ImportError:
        print("OpenCV not installed")
    ref = [pillow(b) for b in blobs]
    for name, fn in decoders.items():
        try:
            same = all(np.array_equal(np.asarray(fn(b), np.int64), r.astype(np.int64))
                       for b, r in zip(blobs[:3], ref))
        except Exception as e:  # a decoder that refuses the files
            print(f"{name}: {type(e).__name__}: {e}")
            continue
        t0 = time.perf_counter()
        for b in blobs:
            fn(b)
        print(f"{name}: {1e3 * (time.perf_counter() - t0) / len(blobs):.2f} ms a frame "
              f"(same pixels as Pillow: {same})")
    ds = bf.open_dataset(args.data, frames=slice(0, len(files)))
    depths = [ds[i].depth_m for i in range(len(ds))]
    for level in (1, 3):
        for kind in ("uint16 mm", "float32"):
            size = t_c = t_d = 0.0
            for d in depths:
                raw = (np.rint(np.nan_to_num(d) * 1000).astype(np.uint16) if kind == "uint16 mm"
                       else d).tobytes()
                t0 = time.perf_counter()
                c = zlib.compress(raw, level)
                t1 = time.perf_counter()
                zlib.decompress(c)
                t_c, t_d, size = t_c + t1 - t0, t_d + time.perf_counter() - t1, size + len(c)
            n = len(depths)
            print(f"zlib level {level}, {kind}: {size / n / 1024:.0f} KB a frame, compress "
                  f"{1e3 * t_c / n:.2f} ms, decompress {1e3 * t_d / n:.2f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
