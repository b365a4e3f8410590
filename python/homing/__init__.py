"""homing: visual SLAM for RGB-D and monocular cameras, driven by an explicit hierarchical
SLAM state machine (Init, Idle, Core with Mapping and Relocalize, Localized, Corrupted Map,
Final).

Frame by frame::

    import homing
    seq = homing.TumSequence("rgbd_dataset_freiburg1_xyz")
    slam = homing.Slam(camera=seq.camera)
    for t, rgb, depth in seq:
        r = slam.track(t, rgb, depth)       # r.pose: 4x4 camera to world, or None
    trajectory, summary = slam.finish()     # N x 8 TUM rows, and a dict

A whole sequence, as the ``homing run`` program does: ``homing.run(sequence, out_dir)``;
evaluation as ``homing eval`` does: ``homing.evaluate(gt, est)``.
"""

from ._homing import (
    Camera,
    FrameResult,
    Slam,
    TumSequence,
    __version__,
    evaluate,
    run,
    synth,
)

__all__ = [
    "Camera",
    "FrameResult",
    "Slam",
    "TumSequence",
    "__version__",
    "evaluate",
    "run",
    "synth",
]
