"""A TUM RGB-D folder through homing.Slam, frame by frame, as your own camera loop would do it:
images decoded with Pillow into numpy arrays, the state timeline printed as it happens, the
final trajectory written in TUM format and evaluated with homing.evaluate (which computes what
evo computes), and with evo's own evo_ape when evo is installed.

    pip install ./python pillow            # evo too, if you want its numbers: pip install evo
    python python/examples/tum_rgbd.py data/rgbd_dataset_freiburg1_xyz [--mono] [--out est.txt]
"""

import argparse
import pathlib
import shutil
import subprocess
import sys

import numpy as np
from PIL import Image

import homing


def read_list(path):
    """rgb.txt / depth.txt: `t file` lines, `#` comments."""
    rows = []
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            t, f = line.split()[:2]
            rows.append((float(t), f))
    return rows


def frames(folder, mono, max_dt=0.02):
    """(t, rgb path, depth path or None), colour and depth associated as TUM's associate.py
    does (or as associations.txt says)."""
    assoc = folder / "associations.txt"
    if assoc.is_file() and not mono:
        for line in assoc.read_text().splitlines():
            if line.strip() and not line.startswith("#"):
                t, rgb, _, depth = line.split()[:4]
                yield float(t), folder / rgb, folder / depth
        return
    rgb = read_list(folder / "rgb.txt")
    if mono:
        for t, f in rgb:
            yield t, folder / f, None
        return
    depth = read_list(folder / "depth.txt")
    # associate.py: every pair within max_dt, closest first, each stamp used once.
    ts_rgb = np.array([t for t, _ in rgb])
    ts_depth = np.array([t for t, _ in depth])
    dt = np.abs(ts_rgb[:, None] - ts_depth[None, :])
    i, j = np.nonzero(dt < max_dt)
    used_rgb, used_depth, pairs = set(), set(), []
    for k in np.argsort(dt[i, j], kind="stable"):
        a, b = int(i[k]), int(j[k])
        if a not in used_rgb and b not in used_depth:
            used_rgb.add(a)
            used_depth.add(b)
            pairs.append((rgb[a][0], folder / rgb[a][1], folder / depth[b][1]))
    yield from sorted(pairs, key=lambda p: p[0])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=pathlib.Path)
    ap.add_argument("--mono", action="store_true", help="depth suppressed (monocular)")
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("trajectory.txt"))
    ap.add_argument("--config", help="a homing config (TOML); default: the built-in defaults")
    args = ap.parse_args()

    # The camera as `homing run` picks it: SEQUENCE/camera.toml, or TUM's from the folder name.
    camera = homing.Camera.from_sequence(args.sequence)
    slam = homing.Slam(config=args.config, camera=camera, mono=args.mono)
    state, n, ms = None, 0, []
    for t, rgb_path, depth_path in frames(args.sequence, args.mono):
        rgb = np.asarray(Image.open(rgb_path).convert("RGB"))
        depth = None if depth_path is None else np.asarray(Image.open(depth_path), dtype=np.uint16)
        r = slam.track(t, rgb, depth)
        n += 1
        ms.append(r.process_ms)
        if r.state != state:
            print(f"frame {r.frame:5d}  t {r.t:.3f}  {r.state:12s} map {r.map}", file=sys.stderr)
            state = r.state
        for p in r.pools_accepted:
            print(f"frame {r.frame:5d}  closure pool {p} accepted", file=sys.stderr)
        for p in r.pools_revoked:
            print(f"frame {r.frame:5d}  closure pool {p} revoked (Corrupted Map)", file=sys.stderr)

    trajectory, summary = slam.finish()
    np.savetxt(args.out, trajectory, fmt="%.6f", header="t tx ty tz qx qy qz qw (camera to world)")
    print(
        f"{summary['poses']} of {n} frames posed, {len(summary['keyframes'])} keyframes, "
        f"{summary['maps']} maps; {np.median(ms):.1f} ms/frame (median); wrote {args.out}",
        file=sys.stderr,
    )

    gt = args.sequence / "groundtruth.txt"
    if not gt.is_file():
        return
    align = "sim3" if args.mono else "se3"
    e = homing.evaluate(gt, args.out, align=align, sequence=args.sequence)
    coverage = "unknown" if e["coverage"] is None else f"{e['coverage'] * 100:.1f} %"
    print(f"homing.evaluate: ATE rmse {e['ate']['stats']['rmse'] * 100:.2f} cm, coverage {coverage}")
    if shutil.which("evo_ape"):
        flags = ["-as"] if args.mono else ["-a"]
        subprocess.run(["evo_ape", "tum", str(gt), str(args.out), *flags], check=False)
    else:
        print("(evo not installed: pip install evo for its report)")


if __name__ == "__main__":
    main()
