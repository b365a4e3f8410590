"""Type stubs of the extension module (re-exported by ``homing``)."""

import os
import pathlib
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

__version__: str

_Path = Union[str, "os.PathLike[str]"]
_Pose = npt.NDArray[np.float64]  # 4x4, camera to world
_TumRows = npt.NDArray[np.float64]  # N x 8: t tx ty tz qx qy qz qw
_Depth = Union[npt.NDArray[np.uint16], npt.NDArray[np.float32], npt.NDArray[np.float64]]
_Frame = Tuple[float, npt.NDArray[np.uint8], Optional[npt.NDArray[np.float32]]]

class Camera:
    """A pinhole camera with radial-tangential distortion: the ``[camera]`` table of a
    config or of a sequence's ``camera.toml``."""

    def __init__(
        self,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        *,
        depth_scale: float = 5000.0,
        k1: float = 0.0,
        k2: float = 0.0,
        p1: float = 0.0,
        p2: float = 0.0,
        k3: float = 0.0,
        fps: float = 30.0,
        readout_s: float = 0.0,
        virtual_baseline_m: float = 0.08,
        name: str = "",
    ) -> None:
        """Raises ValueError for values out of range (e.g. cx outside the image)."""
    @staticmethod
    def from_sequence(dir: _Path) -> "Camera":
        """The camera ``homing run --sequence DIR`` picks: DIR/camera.toml, else TUM's
        freiburg1/2/3 from the folder's name."""
    @staticmethod
    def load(path: _Path) -> "Camera":
        """The ``[camera]`` table of a TOML file."""
    def to_dict(self) -> Dict[str, Any]:
        """The camera's keys (what ``camera=`` also takes)."""
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def depth_scale(self) -> float:
        """Depth units per metre (TUM: 5000)."""
    @property
    def k(self) -> npt.NDArray[np.float64]:
        """The 3x3 intrinsic matrix."""

class FrameResult:
    """What one frame gave."""

    @property
    def frame(self) -> int:
        """The frame's index (0, 1, ... in the order frames were given)."""
    @property
    def t(self) -> float: ...
    @property
    def pose(self) -> Optional[_Pose]:
        """Camera to world (4x4) in the world of ``map``; None when the frame was not
        tracked. Later corrections (loops, merges, Final) move past poses: see
        ``Slam.trajectory``."""
    @property
    def tracked(self) -> bool: ...
    @property
    def map(self) -> Optional[int]:
        """The map the frame is in."""
    @property
    def state(self) -> str:
        """The state(s) after the frame, as states.csv names them (e.g. ``Core(M&R)``,
        ``Localized``, ``CorruptedMap``)."""
    @property
    def transitions(self) -> List[Tuple[str, str, str]]:
        """Transitions taken on the frame, in order: (from, trigger, to)."""
    @property
    def flags(self) -> Dict[str, bool]:
        """initialized, able_to_track, able_to_localize, consistent_map."""
    @property
    def inliers(self) -> Optional[int]:
        """Tracked inliers, when the tracker ran."""
    @property
    def pools_accepted(self) -> List[int]:
        """Closure pools (loops, relocalizations, merges) accepted on this frame."""
    @property
    def pools_revoked(self) -> List[int]:
        """Pools the Corrupted Map state revoked on this frame."""
    @property
    def earlier_frames(self) -> List[int]:
        """Earlier frames posed on this frame: without depth, the frames the two-view
        initializer waited on, posed once their map started (in `Slam.trajectory()` from now
        on)."""
    @property
    def process_ms(self) -> float:
        """Milliseconds homing spent on the frame (without the Python call around it)."""

class Slam:
    """A SLAM session: Init on construction, ``track`` per frame, Final on ``finish`` or
    ``request_stop``. Once finished, it takes no more frames."""

    def __init__(
        self,
        config: Union[None, _Path, Mapping[str, Any]] = None,
        camera: Union[None, Camera, _Path, Mapping[str, Any]] = None,
        *,
        mono: Optional[bool] = None,
        threaded: bool = False,
    ) -> None:
        """``config``: None (the defaults), a TOML file or a dict of its keys (unknown keys
        are refused). ``camera``: a Camera, a TOML file with a ``[camera]`` table (a
        sequence's camera.toml) or a dict of its keys; None takes the config's ``[camera]``.
        ``mono`` overrides the config's ``sequence.mono``. Dict values must be what JSON holds
        (numbers, strings, booleans, lists, dicts). ``threaded``: local BA on its own
        thread (faster, not bit-reproducible); the default is deterministic."""
    @staticmethod
    def load_map(
        path: _Path,
        config: Union[None, _Path, Mapping[str, Any]] = None,
        camera: Union[None, Camera, _Path, Mapping[str, Any]] = None,
        *,
        mono: Optional[bool] = None,
        threaded: bool = False,
    ) -> "Slam":
        """A session that starts in an atlas saved earlier (``save_map``, ``homing run
        --save-map``); refuses an atlas of another camera or modality (ValueError)."""
    def track(
        self,
        t: float,
        rgb: npt.NDArray[np.uint8],
        depth: Optional[_Depth] = None,
        *,
        bgr: bool = False,
    ) -> FrameResult:
        """One frame. ``t``: seconds, later than the previous frame's. ``rgb``: HxWx3 uint8,
        RGB order (``bgr=True`` for OpenCV's). ``depth``: HxW uint16 in the sensor's units
        (``camera.depth_scale`` per metre) or float32/float64 metres, 0 = no reading; None =
        no depth. Arrays of any strides are accepted (copied when not C-contiguous). Raises ValueError for a wrong dtype or shape, an image size other than the
        camera's, a stamp that does not follow the previous one, or a finished session. The
        GIL is released while the frame is processed."""
    def trajectory(self) -> _TumRows:
        """Every frame posed so far, camera to world, with the corrections so far applied."""
    def maps(self) -> List[Dict[str, Any]]:
        """The maps: ``id``, ``keyframe_ids``, ``keyframes`` (N x 8 TUM rows, camera to
        world) and ``points`` (M x 3, world)."""
    @property
    def frames(self) -> int:
        """Frames given so far."""
    @property
    def camera(self) -> Camera: ...
    @property
    def mono(self) -> bool: ...
    def finish(self, out_dir: Optional[_Path] = None) -> Tuple[_TumRows, Dict[str, Any]]:
        """End of data: Final with its refinement. Returns the final trajectory (N x 8 TUM
        rows) and a summary: final_state, frames, poses, maps, trajectory_frames,
        trajectory_maps, keyframes (N x 8), keyframe_maps, states (states.csv's rows),
        closures (closures.csv's rows), discarded (poses that did not stand, and why),
        merges (every merge of two maps, with the frame that confirmed it or None),
        lift_offs (monocular: where each rotation-only stretch ended, what its panoramic
        keyframes' bearings did there, and whether the map went on). With
        ``out_dir``, also writes trajectory.txt, keyframes.txt, states.csv and closures.csv
        as ``homing run`` does."""
    def request_stop(
        self, out_dir: Optional[_Path] = None
    ) -> Tuple[_TumRows, Dict[str, Any]]:
        """The user's stop (the Interruptible state): Final with its refinement cut short;
        returns what ``finish`` returns."""
    def result(self, out_dir: Optional[_Path] = None) -> Tuple[_TumRows, Dict[str, Any]]:
        """What ``finish`` or ``request_stop`` returned, again (e.g. after writing to
        ``out_dir`` failed); ValueError before the session is finished."""
    def save_map(self, path: _Path) -> None:
        """Saves the atlas, atomically."""

class TumSequence:
    """A TUM RGB-D folder read as ``homing run`` reads it. ``seq[i]`` is ``(t, rgb, depth)``:
    rgb HxWx3 uint8, depth HxW float32 metres (None when monocular)."""

    def __init__(
        self,
        dir: _Path,
        camera: Union[None, Camera, _Path, Mapping[str, Any]] = None,
        *,
        mono: bool = False,
        max_association_dt: float = 0.02,
    ) -> None:
        """``camera`` None: DIR/camera.toml, else TUM's from the folder name. Raises
        FileNotFoundError / ValueError for a missing or malformed folder."""
    def __len__(self) -> int: ...
    def __getitem__(self, i: int) -> _Frame:
        """Frame ``i`` (negative counts from the end); IndexError past the end."""
    def __iter__(self) -> Iterator[_Frame]: ...
    @property
    def camera(self) -> Camera: ...
    @property
    def timestamps(self) -> List[float]: ...
    def groundtruth(self) -> Optional[_TumRows]:
        """groundtruth.txt as N x 8 TUM rows; None when the folder has none."""

def run(
    sequence: _Path,
    out_dir: _Path,
    *,
    config: Optional[_Path] = None,
    mono: bool = False,
    drops: Sequence[str] = (),
    faults: Sequence[str] = (),
    fault_rates: Sequence[str] = (),
    seed: int = 0,
    depth_shift: Optional[str] = None,
    eval: bool = True,
    load_map: Optional[_Path] = None,
    save_map: Optional[_Path] = None,
    threaded: bool = False,
    strict_input: bool = False,
    controller: Optional[str] = None,
    no_loop_closing: bool = False,
    mcap_log: bool = False,
) -> Dict[str, Any]:
    """``homing run`` on a TUM folder: the run files written into ``out_dir``; returns
    summary.json as a dict. Options as the program's: drops like ``["229:259"]``, faults
    like ``["black@229-258"]``, fault_rates like ``["foreign:0.05"]``, depth_shift like
    ``"3"`` or ``"2,-1"``, controller "ours" (default), "orbslam2", "proslam" or "ldso". The
    GIL is released during the run; Ctrl-C takes effect when it returns."""

def evaluate(
    gt: Optional[_Path] = None,
    est: Optional[_Path] = None,
    *,
    run: Optional[_Path] = None,
    align: str = "se3",
    rpe_delta: float = 1.0,
    rpe_unit: str = "s",
    all_pairs: bool = False,
    max_dt: float = 0.02,
    sequence: Optional[_Path] = None,
) -> Dict[str, Any]:
    """``homing eval``: an estimate against ground truth, as ``homing eval --json`` prints
    it (ate, rpe, coverage; with ``run``, the run's closures judged and each map's ATE).
    align: "se3" (RGB-D), "sim3" (monocular) or "none"."""

def synth(
    scenario: str,
    out_dir: _Path,
    *,
    small: bool = True,
    seed: int = 1,
    max_frames: Optional[int] = None,
    clean: bool = False,
) -> List[pathlib.Path]:
    """Renders a synthetic scenario (desk, loop, aliasing, revisit, case-study) into TUM
    folders with ground truth, as ``homing-datasets synth`` does; returns the folders."""
