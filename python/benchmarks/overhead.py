"""The per-frame overhead of the Python call over the Rust API it wraps.

For each frame, the wall time of `slam.track(t, rgb, depth)` as Python sees it, against
`FrameResult.process_ms`, the time spent inside the Rust API call (`Slam::track_buffers`) for
the same frame. The difference is what the binding adds: checking and copying the numpy
arrays, releasing and taking back the GIL, building the result. Frames are decoded beforehand
(homing.TumSequence), so decoding is not counted.

    python python/benchmarks/overhead.py ../shared/datasets/rgbd_dataset_freiburg1_xyz_first300
"""

import pathlib
import sys
import time

import numpy as np

import homing


def main():
    seq_dir = pathlib.Path(sys.argv[1])
    mono = "--mono" in sys.argv
    seq = homing.TumSequence(seq_dir, mono=mono)
    frames = [seq[i] for i in range(len(seq))]
    slam = homing.Slam(camera=seq.camera, mono=mono)
    wall, inside = [], []
    for t, rgb, depth in frames:
        if depth is not None:
            depth = np.round(depth * seq.camera.depth_scale).astype(np.uint16)
        t0 = time.perf_counter()
        r = slam.track(t, rgb, depth)
        wall.append((time.perf_counter() - t0) * 1e3)
        inside.append(r.process_ms)
    slam.finish()
    wall, inside = np.array(wall), np.array(inside)
    over = wall - inside
    print(f"{seq_dir.name}: {len(frames)} frames, {'monocular' if mono else 'RGB-D'}, "
          f"{seq.camera.width}x{seq.camera.height}")
    print(f"  Python call  median {np.median(wall):7.3f} ms   p90 {np.percentile(wall, 90):7.3f} ms")
    print(f"  Rust API     median {np.median(inside):7.3f} ms   p90 {np.percentile(inside, 90):7.3f} ms")
    print(f"  overhead     median {np.median(over):7.3f} ms   p90 {np.percentile(over, 90):7.3f} ms   "
          f"max {over.max():7.3f} ms")


if __name__ == "__main__":
    main()
