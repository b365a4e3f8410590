//! `homing._homing`: the Python face of [`homing::slam::Slam`], of `homing run` and of
//! `homing eval`. Arrays come in and go out as numpy arrays; structured results (summaries,
//! evaluations) as the same JSON the program writes, loaded into dicts. Every error is a Python
//! exception (`ValueError`, `FileNotFoundError`), never a panic across the boundary.

use homing::atlas::{Atlas, AtlasCamera};
use homing::config::{CameraConfig, Config, resolve_camera};
use homing::io::tum::{FrameSource, StampedPose, TumSequence as RsTum};
use homing::outputs::{ClosureRow, Flags, RunOutputs, StateRow};
use homing::slam::{DepthBuffer, FrameResult as RsFrame, Slam as RsSlam, SlamOutput};
use nalgebra::Isometry3;
use numpy::ndarray::{Array2, Array3};
use numpy::{IntoPyArray, PyArray2, PyArrayDyn, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::exceptions::{PyFileNotFoundError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

/// A homing error as the Python exception a caller expects: a file that is not there is
/// `FileNotFoundError`, everything else about the input `ValueError`.
fn py_err(e: homing::Error) -> PyErr {
    match &e {
        homing::Error::File { path, .. } if !path.exists() => {
            PyFileNotFoundError::new_err(e.to_string())
        }
        _ => PyValueError::new_err(e.to_string()),
    }
}

/// A Rust value as the dict (or list) its JSON gives.
fn to_py<'py, T: serde::Serialize>(py: Python<'py>, v: &T) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(v).map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// A Python dict as a Rust value, through JSON (so serde's checks apply: unknown keys, types).
fn from_py<T: serde::de::DeserializeOwned>(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<T> {
    let py = obj.py();
    let text: String = py
        .import("json")?
        .call_method1("dumps", (obj,))
        .map_err(|e| {
            PyValueError::new_err(format!(
                "{what}: values must be numbers, strings, booleans, lists or tables: {e}"
            ))
        })?
        .extract()?;
    serde_json::from_str(&text).map_err(|e| PyValueError::new_err(format!("{what}: {e}")))
}

/// A mapping (a dict or any other) as a dict; `None` for anything else.
fn as_dict<'py>(obj: &Bound<'py, PyAny>) -> PyResult<Option<Bound<'py, PyAny>>> {
    if obj.is_instance_of::<PyDict>() {
        return Ok(Some(obj.clone()));
    }
    if obj.cast::<pyo3::types::PyMapping>().is_ok() {
        return Ok(Some(
            obj.py().get_type::<PyDict>().call1((obj,))?.into_any(),
        ));
    }
    Ok(None)
}

/// The config a caller gives: none (the defaults), a TOML file, or a dict of the file's keys.
fn config_from(obj: Option<&Bound<'_, PyAny>>) -> PyResult<Config> {
    let Some(obj) = obj.filter(|o| !o.is_none()) else {
        return Ok(Config::default());
    };
    if let Some(d) = as_dict(obj)? {
        let cfg: Config = from_py(&d, "config")?;
        cfg.validate()
            .map_err(|(key, msg)| PyValueError::new_err(format!("config: {key}: {msg}")))?;
        return Ok(cfg);
    }
    let path: PathBuf = obj.extract().map_err(|_| {
        PyValueError::new_err("config must be None, a path to a TOML file or a dict")
    })?;
    Config::load(&path).map_err(py_err)
}

/// The camera a caller gives: a `Camera`, a TOML file with a `[camera]` table, a dict of that
/// table's keys, or none (the config's `[camera]`).
fn camera_from(obj: Option<&Bound<'_, PyAny>>, config: &Config) -> PyResult<CameraConfig> {
    let Some(obj) = obj.filter(|o| !o.is_none()) else {
        return config.camera.clone().ok_or_else(|| {
            PyValueError::new_err(
                "no camera: pass camera= (a homing.Camera, a camera.toml path or a dict), or a \
                 config with a [camera] table",
            )
        });
    };
    if let Ok(c) = obj.cast::<Camera>() {
        return Ok(c.get().inner.clone());
    }
    if let Some(d) = as_dict(obj)? {
        return checked_camera(from_py(&d, "camera")?);
    }
    let path: PathBuf = obj.extract().map_err(|_| {
        PyValueError::new_err("camera must be a homing.Camera, a path to a TOML file or a dict")
    })?;
    camera_file(&path)
}

fn camera_file(path: &Path) -> PyResult<CameraConfig> {
    Config::load(path)
        .map_err(py_err)?
        .camera
        .ok_or_else(|| PyValueError::new_err(format!("{}: has no [camera] table", path.display())))
}

/// The config's range checks on a camera.
fn checked_camera(cam: CameraConfig) -> PyResult<CameraConfig> {
    let cfg = Config {
        camera: Some(cam),
        ..Config::default()
    };
    cfg.validate()
        .map_err(|(key, msg)| PyValueError::new_err(format!("{key}: {msg}")))?;
    Ok(cfg.camera.expect("set above"))
}

/// A sequence folder must be there before anything is read from it (or guessed from its name).
fn sequence_folder(dir: &Path) -> PyResult<()> {
    if !dir.exists() {
        return Err(PyFileNotFoundError::new_err(format!(
            "{}: no such folder",
            dir.display()
        )));
    }
    if !dir.is_dir() {
        return Err(PyValueError::new_err(format!(
            "{}: is not a folder",
            dir.display()
        )));
    }
    Ok(())
}

/// A pose as a 4×4 matrix (camera to world).
fn matrix<'py>(py: Python<'py>, p: &Isometry3<f64>) -> Bound<'py, PyArray2<f64>> {
    let m = p.to_homogeneous();
    Array2::from_shape_fn((4, 4), |(r, c)| m[(r, c)]).into_pyarray(py)
}

/// Poses as TUM rows: `t tx ty tz qx qy qz qw`, N×8.
fn tum_rows<'py>(py: Python<'py>, poses: &[StampedPose]) -> Bound<'py, PyArray2<f64>> {
    let mut a = Array2::zeros((poses.len(), 8));
    for (i, p) in poses.iter().enumerate() {
        let (t, q) = (p.pose.translation.vector, p.pose.rotation.coords);
        for (j, v) in [p.t, t.x, t.y, t.z, q.x, q.y, q.z, q.w]
            .into_iter()
            .enumerate()
        {
            a[(i, j)] = v;
        }
    }
    a.into_pyarray(py)
}

fn flags_dict<'py>(py: Python<'py>, f: &Flags) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("initialized", f.initialized)?;
    d.set_item("able_to_track", f.able_to_track)?;
    d.set_item("able_to_localize", f.able_to_localize)?;
    d.set_item("consistent_map", f.consistent_map)?;
    Ok(d)
}

fn state_rows<'py>(py: Python<'py>, rows: &[StateRow]) -> PyResult<Bound<'py, PyList>> {
    let out = PyList::empty(py);
    for r in rows {
        let d = PyDict::new(py);
        d.set_item("frame", r.frame)?;
        d.set_item("t", r.t)?;
        d.set_item("state", &r.state)?;
        d.set_item("from", r.transition.as_ref().map(|t| t.from.clone()))?;
        d.set_item("trigger", r.transition.as_ref().map(|t| t.trigger.clone()))?;
        d.set_item("flags", flags_dict(py, &r.flags)?)?;
        d.set_item("map", r.map)?;
        out.append(d)?;
    }
    Ok(out)
}

fn closure_rows<'py>(py: Python<'py>, rows: &[ClosureRow]) -> PyResult<Bound<'py, PyList>> {
    let out = PyList::empty(py);
    for r in rows {
        let d = PyDict::new(py);
        d.set_item("frame", r.frame)?;
        d.set_item("kind", &r.kind)?;
        d.set_item("t_query", r.t_query)?;
        d.set_item("t_match", r.t_match)?;
        d.set_item("map_query", r.map_query)?;
        d.set_item("map_match", r.map_match)?;
        d.set_item("matched_kf", r.matched_kf)?;
        d.set_item("relative", r.relative.as_ref().map(|p| matrix(py, p)))?;
        d.set_item("inliers", r.inliers)?;
        d.set_item("verdict", &r.verdict)?;
        d.set_item("pool", r.pool)?;
        out.append(d)?;
    }
    Ok(out)
}

/// A pinhole camera with radial-tangential distortion: the `[camera]` table of a config or of
/// a sequence's `camera.toml`.
#[pyclass(module = "homing", frozen)]
#[derive(Clone)]
struct Camera {
    inner: CameraConfig,
}

#[pymethods]
impl Camera {
    #[new]
    #[pyo3(signature = (fx, fy, cx, cy, width, height, *, depth_scale = 5000.0, k1 = 0.0,
        k2 = 0.0, p1 = 0.0, p2 = 0.0, k3 = 0.0, fps = 30.0, readout_s = 0.0,
        virtual_baseline_m = homing::config::default_virtual_baseline(), name = String::new()))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        width: i64,
        height: i64,
        depth_scale: f64,
        k1: f64,
        k2: f64,
        p1: f64,
        p2: f64,
        k3: f64,
        fps: f64,
        readout_s: f64,
        virtual_baseline_m: f64,
        name: String,
    ) -> PyResult<Self> {
        let size = |what: &str, v: i64| {
            u32::try_from(v)
                .ok()
                .filter(|&v| (1..=16384).contains(&v))
                .ok_or_else(|| {
                    PyValueError::new_err(format!("camera.{what} must be 1 to 16384, got {v}"))
                })
        };
        let (width, height) = (size("width", width)?, size("height", height)?);
        let inner = checked_camera(CameraConfig {
            name,
            fx,
            fy,
            cx,
            cy,
            k1,
            k2,
            p1,
            p2,
            k3,
            width,
            height,
            depth_scale,
            fps,
            readout_s,
            virtual_baseline_m,
        })?;
        Ok(Self { inner })
    }

    /// The camera `homing run --sequence DIR` picks: DIR/camera.toml, else TUM's freiburg1/2/3
    /// from the folder's name.
    #[staticmethod]
    fn from_sequence(dir: PathBuf) -> PyResult<Self> {
        sequence_folder(&dir)?;
        let (inner, _) = resolve_camera(&Config::default(), None, &dir).map_err(py_err)?;
        Ok(Self { inner })
    }

    /// The `[camera]` table of a TOML file.
    #[staticmethod]
    fn load(path: PathBuf) -> PyResult<Self> {
        Ok(Self {
            inner: camera_file(&path)?,
        })
    }

    /// The camera's keys, as a dict (what `camera=` also takes).
    fn to_dict<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py(py, &self.inner)
    }

    #[getter]
    fn width(&self) -> u32 {
        self.inner.width
    }
    #[getter]
    fn height(&self) -> u32 {
        self.inner.height
    }
    #[getter]
    fn depth_scale(&self) -> f64 {
        self.inner.depth_scale
    }
    /// The 3×3 intrinsic matrix.
    #[getter]
    fn k<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let c = &self.inner;
        let m = [[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]];
        Array2::from_shape_fn((3, 3), |(r, k)| m[r][k]).into_pyarray(py)
    }

    fn __repr__(&self) -> String {
        let c = &self.inner;
        format!(
            "homing.Camera(fx={}, fy={}, cx={}, cy={}, width={}, height={}, depth_scale={}{})",
            c.fx,
            c.fy,
            c.cx,
            c.cy,
            c.width,
            c.height,
            c.depth_scale,
            if c.name.is_empty() {
                String::new()
            } else {
                format!(", name={:?}", c.name)
            }
        )
    }
}

/// What one frame gave (`Slam.track`).
#[pyclass(module = "homing", frozen)]
struct FrameResult {
    inner: RsFrame,
    process_ms: f64,
}

#[pymethods]
impl FrameResult {
    /// The frame's index (0, 1, … in the order frames were given).
    #[getter]
    fn frame(&self) -> usize {
        self.inner.frame
    }
    #[getter]
    fn t(&self) -> f64 {
        self.inner.t
    }
    /// Camera to world as a 4×4 array, in the world of `map`; None when not tracked.
    #[getter]
    fn pose<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray2<f64>>> {
        self.inner.pose_wc.as_ref().map(|p| matrix(py, p))
    }
    #[getter]
    fn tracked(&self) -> bool {
        self.inner.pose_wc.is_some()
    }
    /// The map the frame is in.
    #[getter]
    fn map(&self) -> Option<u32> {
        self.inner.map
    }
    /// The state(s) after the frame, as states.csv names them (e.g. "Core(M&R)").
    #[getter]
    fn state(&self) -> String {
        self.inner.state.clone()
    }
    /// Transitions taken on the frame: (from, trigger, to) tuples.
    #[getter]
    fn transitions(&self) -> Vec<(String, String, String)> {
        self.inner
            .transitions
            .iter()
            .map(|t| {
                (
                    t.transition.from.clone(),
                    t.transition.trigger.clone(),
                    t.to.clone(),
                )
            })
            .collect()
    }
    /// The four flags the state machine's guards read.
    #[getter]
    fn flags<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        flags_dict(py, &self.inner.flags)
    }
    #[getter]
    fn inliers(&self) -> Option<usize> {
        self.inner.inliers
    }
    /// Closure pools (loops, relocalizations, merges) accepted on this frame.
    #[getter]
    fn pools_accepted(&self) -> Vec<u32> {
        self.inner.pools_accepted.clone()
    }
    /// Pools the Corrupted Map state revoked on this frame.
    #[getter]
    fn pools_revoked(&self) -> Vec<u32> {
        self.inner.pools_revoked.clone()
    }
    /// Earlier frames posed on this frame: without depth, the frames the two-view initializer
    /// waited on, posed once their map started (in `Slam.trajectory()` from now on).
    #[getter]
    fn earlier_frames(&self) -> Vec<usize> {
        self.inner.earlier_frames.clone()
    }
    /// Milliseconds homing spent on the frame (the Rust call, without the Python around it).
    #[getter]
    fn process_ms(&self) -> f64 {
        self.process_ms
    }
    fn __repr__(&self) -> String {
        format!(
            "homing.FrameResult(frame={}, t={:.6}, state={:?}, map={:?}, tracked={})",
            self.inner.frame,
            self.inner.t,
            self.inner.state,
            self.inner.map,
            self.inner.pose_wc.is_some()
        )
    }
}

/// A colour image as the row-major RGB bytes the camera's size needs.
fn rgb_bytes(a: &Bound<'_, PyAny>, cam: &CameraConfig, bgr: bool) -> PyResult<Vec<u8>> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let Ok(arr) = a.cast::<PyArrayDyn<u8>>() else {
        return Err(PyValueError::new_err(format!(
            "rgb must be an H×W×3 uint8 numpy array ({h}×{w}×3 for this camera); got {}",
            describe(a)
        )));
    };
    if arr.shape() != [h, w, 3] {
        return Err(PyValueError::new_err(format!(
            "rgb has shape {:?}; this camera needs {h}×{w}×3",
            arr.shape()
        )));
    }
    let mut v = values(arr)?;
    if bgr {
        for px in v.chunks_exact_mut(3) {
            px.swap(0, 2);
        }
    }
    Ok(v)
}

/// An array's values in row-major order. Read in place only when it is C-contiguous and
/// aligned; anything else (a slice, a field of a structured array, a buffer at an odd offset)
/// is first made so by numpy (`numpy.require(a, requirements="CA")`), never reinterpreted.
fn values<T: numpy::Element + Copy>(arr: &Bound<'_, PyArrayDyn<T>>) -> PyResult<Vec<T>> {
    let aligned = (arr.data() as usize).is_multiple_of(std::mem::align_of::<T>());
    if arr.is_c_contiguous() && aligned {
        let ro = arr
            .try_readonly()
            .map_err(|e| PyValueError::new_err(format!("the array cannot be read: {e}")))?;
        return Ok(ro
            .as_slice()
            .map_err(|e| PyValueError::new_err(e.to_string()))?
            .to_vec());
    }
    let py = arr.py();
    let copy = py
        .import("numpy")?
        .call_method1("require", (arr, py.None(), "CA"))?;
    let copy = copy
        .cast::<PyArrayDyn<T>>()
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    let ro = copy
        .try_readonly()
        .map_err(|e| PyValueError::new_err(format!("the array cannot be read: {e}")))?;
    Ok(ro
        .as_slice()
        .map_err(|e| PyValueError::new_err(e.to_string()))?
        .to_vec())
}

/// Depth as the camera's size needs it: the sensor's uint16 units, or metres.
enum Depth {
    Units(Vec<u16>),
    Metres(Vec<f32>),
}

fn depth_values(a: &Bound<'_, PyAny>, cam: &CameraConfig) -> PyResult<Depth> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let shape_ok = |shape: &[usize]| {
        if shape == [h, w] {
            Ok(())
        } else {
            Err(PyValueError::new_err(format!(
                "depth has shape {shape:?}; this camera needs {h}×{w}"
            )))
        }
    };
    if let Ok(arr) = a.cast::<PyArrayDyn<u16>>() {
        shape_ok(arr.shape())?;
        return Ok(Depth::Units(values(arr)?));
    }
    if let Ok(arr) = a.cast::<PyArrayDyn<f32>>() {
        shape_ok(arr.shape())?;
        return Ok(Depth::Metres(values(arr)?));
    }
    if let Ok(arr) = a.cast::<PyArrayDyn<f64>>() {
        shape_ok(arr.shape())?;
        return Ok(Depth::Metres(
            values(arr)?.into_iter().map(|m| m as f32).collect(),
        ));
    }
    Err(PyValueError::new_err(format!(
        "depth must be an H×W numpy array of uint16 (the sensor's units, {} per metre) or \
         float32 metres; got {}",
        cam.depth_scale,
        describe(a)
    )))
}

/// What a wrong argument was, for the message.
fn describe(a: &Bound<'_, PyAny>) -> String {
    let dtype = a
        .getattr("dtype")
        .map(|d| d.to_string())
        .unwrap_or_default();
    let shape = a
        .getattr("shape")
        .map(|s| s.to_string())
        .unwrap_or_default();
    match (dtype.is_empty(), shape.is_empty()) {
        (false, false) => format!("an array of dtype {dtype} and shape {shape}"),
        _ => format!(
            "a {}",
            a.get_type()
                .name()
                .map(|n| n.to_string())
                .unwrap_or_default()
        ),
    }
}

/// A SLAM session: Init on construction, `track` per frame, Final on `finish`.
#[pyclass(module = "homing")]
struct Slam {
    inner: Mutex<RsSlam>,
    camera: CameraConfig,
    mono: bool,
    /// What Final gave, kept so that a failed write of the files loses nothing (`result`).
    output: Mutex<Option<SlamOutput>>,
}

impl Slam {
    /// Runs `f` on the session without the GIL: other Python threads go on meanwhile, also
    /// while this one waits for another thread's frame. A panic (a bug) becomes a
    /// `RuntimeError` instead of unwinding into Python.
    fn with<R: Send>(
        &self,
        py: Python<'_>,
        f: impl FnOnce(&mut RsSlam) -> R + Send,
    ) -> PyResult<R> {
        py.detach(|| {
            let mut s = self
                .inner
                .lock()
                .map_err(|_| PyRuntimeError::new_err("the session failed earlier (a bug)"))?;
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| f(&mut s)))
                .map_err(|_| PyRuntimeError::new_err("homing failed on this call (a bug)"))
        })
    }

    /// Final (by end of data or the user's stop), then its output. The output folder is made
    /// first, so a folder that cannot be made fails before the session ends; what Final gave
    /// is kept for `result`.
    fn end<'py>(
        &self,
        py: Python<'py>,
        out_dir: Option<PathBuf>,
        stop: bool,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyDict>)> {
        if let Some(dir) = &out_dir {
            RunOutputs::create(dir).map_err(py_err)?;
        }
        let out = self
            .with(py, |s| if stop { s.request_stop() } else { s.finish() })?
            .map_err(py_err)?;
        *self
            .output
            .lock()
            .map_err(|_| PyRuntimeError::new_err("the session failed earlier (a bug)"))? =
            Some(out.clone());
        self.output(py, out, out_dir)
    }

    /// The output a finished session gives, as (trajectory, summary); the run files written to
    /// `out_dir` when given.
    fn output<'py>(
        &self,
        py: Python<'py>,
        out: SlamOutput,
        out_dir: Option<PathBuf>,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyDict>)> {
        if let Some(dir) = &out_dir {
            let o = RunOutputs::create(dir).map_err(py_err)?;
            o.write_trajectory(&out.trajectory).map_err(py_err)?;
            o.write_keyframes(&out.keyframes).map_err(py_err)?;
            o.write_states(&out.states).map_err(py_err)?;
            o.write_closures(&out.closures).map_err(py_err)?;
        }
        let d = PyDict::new(py);
        d.set_item("final_state", &out.final_state)?;
        d.set_item("frames", self.with(py, |s| s.delivered())?)?;
        d.set_item("poses", out.trajectory.len())?;
        d.set_item("maps", self.with(py, |s| s.atlas().maps.len())?)?;
        d.set_item("trajectory_frames", out.trajectory_frames.clone())?;
        d.set_item("trajectory_maps", out.trajectory_maps.clone())?;
        let kf: Vec<StampedPose> = out.keyframes.iter().map(|(p, _)| *p).collect();
        d.set_item("keyframes", tum_rows(py, &kf))?;
        d.set_item(
            "keyframe_maps",
            out.keyframes.iter().map(|(_, m)| *m).collect::<Vec<_>>(),
        )?;
        d.set_item("states", state_rows(py, &out.states)?)?;
        d.set_item("closures", closure_rows(py, &out.closures)?)?;
        d.set_item("discarded", to_py(py, &out.discarded)?)?;
        d.set_item("merges", to_py(py, &out.merges)?)?;
        d.set_item("lift_offs", to_py(py, &out.lift_offs)?)?;
        Ok((tum_rows(py, &out.trajectory), d))
    }
}

#[pymethods]
impl Slam {
    /// A new session (Init). `config`: None (the defaults), a TOML path or a dict of the
    /// config file's keys. `camera`: a `Camera`, a TOML path with a `[camera]` table (a
    /// sequence's camera.toml) or a dict; None takes the config's `[camera]`. `mono` overrides
    /// the config's `sequence.mono`.
    #[new]
    #[pyo3(signature = (config = None, camera = None, *, mono = None, threaded = false))]
    fn new(
        config: Option<&Bound<'_, PyAny>>,
        camera: Option<&Bound<'_, PyAny>>,
        mono: Option<bool>,
        threaded: bool,
    ) -> PyResult<Self> {
        let config = config_from(config)?;
        let camera = camera_from(camera, &config)?;
        let mut config = config;
        if let Some(m) = mono {
            config.sequence.mono = m;
        }
        let mut inner = RsSlam::new(&config, &camera).map_err(py_err)?;
        if threaded {
            inner.set_threaded();
        }
        Ok(Self {
            inner: Mutex::new(inner),
            camera,
            mono: config.sequence.mono,
            output: Mutex::new(None),
        })
    }

    /// A session that starts in an atlas saved earlier (`save_map`, `homing run
    /// --save-map`): its first frames relocalize in the loaded maps.
    #[staticmethod]
    #[pyo3(signature = (path, config = None, camera = None, *, mono = None, threaded = false))]
    fn load_map(
        path: PathBuf,
        config: Option<&Bound<'_, PyAny>>,
        camera: Option<&Bound<'_, PyAny>>,
        mono: Option<bool>,
        threaded: bool,
    ) -> PyResult<Self> {
        let s = Self::new(config, camera, mono, threaded)?;
        let atlas = Atlas::load(&path, &AtlasCamera::from(&s.camera), s.mono).map_err(py_err)?;
        let inner = s
            .inner
            .into_inner()
            .map_err(|_| PyRuntimeError::new_err("poisoned"))?;
        Ok(Self {
            inner: Mutex::new(inner.with_atlas(atlas)),
            camera: s.camera,
            mono: s.mono,
            output: Mutex::new(None),
        })
    }

    /// One frame. `t`: seconds, later than the previous frame's. `rgb`: H×W×3 uint8 in RGB
    /// order (`bgr=True` for OpenCV's order). `depth`: H×W uint16 in the sensor's units
    /// (`camera.depth_scale` per metre) or float32 metres, 0 = no reading; None = no depth
    /// (a monocular session ignores depth). The GIL is released while the frame is processed.
    #[pyo3(signature = (t, rgb, depth = None, *, bgr = false))]
    fn track(
        &self,
        py: Python<'_>,
        t: f64,
        rgb: &Bound<'_, PyAny>,
        depth: Option<&Bound<'_, PyAny>>,
        bgr: bool,
    ) -> PyResult<FrameResult> {
        let rgb = rgb_bytes(rgb, &self.camera, bgr)?;
        let depth = match depth.filter(|d| !d.is_none()) {
            Some(d) => Some(depth_values(d, &self.camera)?),
            None => None,
        };
        let (r, ms) = self.with(py, |s| {
            let start = Instant::now();
            let buf = match &depth {
                Some(Depth::Units(v)) => Some(DepthBuffer::Units(v)),
                Some(Depth::Metres(v)) => Some(DepthBuffer::Metres(v)),
                None => None,
            };
            let r = s.track_buffers(t, &rgb, buf);
            (r, start.elapsed().as_secs_f64() * 1e3)
        })?;
        Ok(FrameResult {
            inner: r.map_err(py_err)?,
            process_ms: ms,
        })
    }

    /// Every frame posed so far, as an N×8 array of TUM rows (t tx ty tz qx qy qz qw, camera
    /// to world), with the corrections made so far applied.
    fn trajectory<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let poses = self.with(py, |s| s.trajectory())?;
        Ok(tum_rows(py, &poses))
    }

    /// The maps as they stand: a list of dicts with the map's `id`, its `keyframes` (N×8 TUM
    /// rows, camera to world), `keyframe_ids` and `points` (M×3, world).
    fn maps<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        let out = PyList::empty(py);
        // Copied out under the lock; the Python objects are made after.
        struct MapCopy {
            id: u32,
            ids: Vec<u32>,
            kfs: Vec<StampedPose>,
            pts: Vec<[f64; 3]>,
        }
        let maps: Vec<MapCopy> = self.with(py, |s| {
            s.atlas()
                .maps
                .values()
                .map(|m| MapCopy {
                    id: m.id,
                    ids: m.keyframes.keys().copied().collect(),
                    kfs: m
                        .keyframes
                        .values()
                        .map(|k| StampedPose {
                            t: k.t,
                            pose: k.pose_cw.inverse(),
                        })
                        .collect(),
                    pts: m
                        .points
                        .values()
                        .map(|p| [p.position.x, p.position.y, p.position.z])
                        .collect(),
                })
                .collect()
        })?;
        for MapCopy { id, ids, kfs, pts } in maps {
            let d = PyDict::new(py);
            d.set_item("id", id)?;
            d.set_item("keyframe_ids", ids)?;
            d.set_item("keyframes", tum_rows(py, &kfs))?;
            let n = pts.len();
            let a = Array2::from_shape_vec((n, 3), pts.into_iter().flatten().collect())
                .expect("n×3 values");
            d.set_item("points", a.into_pyarray(py))?;
            out.append(d)?;
        }
        Ok(out)
    }

    /// Frames given so far.
    #[getter]
    fn frames(&self, py: Python<'_>) -> PyResult<usize> {
        self.with(py, |s| s.delivered())
    }

    #[getter]
    fn camera(&self) -> Camera {
        Camera {
            inner: self.camera.clone(),
        }
    }

    #[getter]
    fn mono(&self) -> bool {
        self.mono
    }

    /// End of data: Final (its refinement), then (trajectory N×8, summary dict). With
    /// `out_dir`, also writes trajectory.txt, keyframes.txt, states.csv and closures.csv there
    /// as `homing run` writes them (not its summary.json and timing.csv).
    #[pyo3(signature = (out_dir = None))]
    fn finish<'py>(
        &self,
        py: Python<'py>,
        out_dir: Option<PathBuf>,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyDict>)> {
        self.end(py, out_dir, false)
    }

    /// The user's stop (Interruptible): Final with its refinement cut short, then what
    /// `finish` gives.
    #[pyo3(signature = (out_dir = None))]
    fn request_stop<'py>(
        &self,
        py: Python<'py>,
        out_dir: Option<PathBuf>,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyDict>)> {
        self.end(py, out_dir, true)
    }

    /// What the finished session gave, again (e.g. after writing to `out_dir` failed).
    #[pyo3(signature = (out_dir = None))]
    fn result<'py>(
        &self,
        py: Python<'py>,
        out_dir: Option<PathBuf>,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyDict>)> {
        let out = self
            .output
            .lock()
            .map_err(|_| PyRuntimeError::new_err("the session failed earlier (a bug)"))?
            .clone()
            .ok_or_else(|| PyValueError::new_err("the session is not finished"))?;
        self.output(py, out, out_dir)
    }

    /// Saves the atlas (written atomically) for a later session (`Slam.load_map`,
    /// `homing run --load-map`).
    fn save_map(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        self.with(py, |s| s.save_atlas(&path))?.map_err(py_err)
    }

    fn __repr__(&self, py: Python<'_>) -> PyResult<String> {
        let (frames, maps) = self.with(py, |s| (s.delivered(), s.atlas().maps.len()))?;
        Ok(format!(
            "homing.Slam({}, {}x{}, {frames} frames, {maps} maps)",
            if self.mono { "monocular" } else { "RGB-D" },
            self.camera.width,
            self.camera.height
        ))
    }
}

/// A TUM RGB-D folder read as `homing run` reads it: `seq[i]` is `(t, rgb, depth)` with
/// `rgb` H×W×3 uint8 and `depth` H×W float32 metres (None when monocular).
#[pyclass(module = "homing", frozen, sequence)]
struct TumSequence {
    inner: RsTum,
    camera: CameraConfig,
}

#[pymethods]
impl TumSequence {
    /// `camera`: as `Slam` takes it; None picks it as `homing run` does (DIR/camera.toml or
    /// TUM's from the folder name).
    #[new]
    #[pyo3(signature = (dir, camera = None, *, mono = false, max_association_dt = 0.02))]
    fn new(
        dir: PathBuf,
        camera: Option<&Bound<'_, PyAny>>,
        mono: bool,
        max_association_dt: f64,
    ) -> PyResult<Self> {
        sequence_folder(&dir)?;
        let camera = match camera.filter(|c| !c.is_none()) {
            Some(c) => camera_from(Some(c), &Config::default())?,
            None => {
                resolve_camera(&Config::default(), None, &dir)
                    .map_err(py_err)?
                    .0
            }
        };
        let inner = RsTum::open(
            &dir,
            camera.width,
            camera.height,
            camera.depth_scale,
            max_association_dt,
            mono,
        )
        .map_err(py_err)?;
        Ok(Self { inner, camera })
    }

    fn __len__(&self) -> usize {
        self.inner.len()
    }

    fn __getitem__<'py>(
        &self,
        py: Python<'py>,
        i: isize,
    ) -> PyResult<(f64, Bound<'py, PyAny>, Option<Bound<'py, PyAny>>)> {
        let n = self.inner.len() as isize;
        let j = if i < 0 { i + n } else { i };
        if j < 0 || j >= n {
            return Err(pyo3::exceptions::PyIndexError::new_err(format!(
                "frame {i} of a sequence of {n}"
            )));
        }
        let f = py.detach(|| self.inner.load(j as usize)).map_err(py_err)?;
        let (w, h) = (f.rgb.width() as usize, f.rgb.height() as usize);
        let rgb = Array3::from_shape_vec((h, w, 3), f.rgb.into_raw())
            .expect("w×h×3 bytes")
            .into_pyarray(py)
            .into_any();
        let depth = f.depth.map(|d| {
            Array2::from_shape_vec((d.height as usize, d.width as usize), d.data)
                .expect("w×h values")
                .into_pyarray(py)
                .into_any()
        });
        Ok((f.t, rgb, depth))
    }

    /// The camera the frames are for.
    #[getter]
    fn camera(&self) -> Camera {
        Camera {
            inner: self.camera.clone(),
        }
    }

    /// The frames' stamps.
    #[getter]
    fn timestamps(&self) -> Vec<f64> {
        self.inner.frames.iter().map(|f| f.t).collect()
    }

    /// The folder's groundtruth.txt as N×8 TUM rows; None when it has none.
    fn groundtruth<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyArray2<f64>>>> {
        Ok(self
            .inner
            .groundtruth()
            .map_err(py_err)?
            .map(|g| tum_rows(py, &g)))
    }
}

/// `homing run`: a whole sequence, the run files written into `out_dir`; returns summary.json
/// as a dict. The options are the program's (see `homing run --help`) for a TUM folder:
/// `drops` like ["229:259"], `faults` like ["black@229-258"], `fault_rates` like
/// ["foreign:0.05"], `controller` one of "ours", "orbslam2", "proslam", "ldso".
#[pyfunction]
#[pyo3(signature = (sequence, out_dir, *, config = None, mono = false, drops = vec![],
    faults = vec![], fault_rates = vec![], seed = 0, depth_shift = None, eval = true,
    load_map = None, save_map = None, threaded = false, strict_input = false, controller = None,
    no_loop_closing = false, mcap_log = false))]
#[allow(clippy::too_many_arguments)]
fn run<'py>(
    py: Python<'py>,
    sequence: PathBuf,
    out_dir: PathBuf,
    config: Option<PathBuf>,
    mono: bool,
    drops: Vec<String>,
    faults: Vec<String>,
    fault_rates: Vec<String>,
    seed: u64,
    depth_shift: Option<String>,
    eval: bool,
    load_map: Option<PathBuf>,
    save_map: Option<PathBuf>,
    threaded: bool,
    strict_input: bool,
    controller: Option<&str>,
    no_loop_closing: bool,
    mcap_log: bool,
) -> PyResult<Bound<'py, PyAny>> {
    use homing::config::ControllerKind;
    let controller = match controller {
        None => None,
        Some("ours") => Some(ControllerKind::Ours),
        Some("orbslam2") => Some(ControllerKind::Orbslam2),
        Some("proslam") => Some(ControllerKind::Proslam),
        Some("ldso") => Some(ControllerKind::Ldso),
        Some(c) => {
            return Err(PyValueError::new_err(format!(
                "controller {c:?}: use \"ours\", \"orbslam2\", \"proslam\" or \"ldso\""
            )));
        }
    };
    fn parse<T: std::str::FromStr>(what: &str, v: &[String]) -> PyResult<Vec<T>>
    where
        T::Err: std::fmt::Display,
    {
        v.iter()
            .map(|s| {
                s.parse()
                    .map_err(|e| PyValueError::new_err(format!("{what} {s:?}: {e}")))
            })
            .collect()
    }
    let perturb = homing::io::perturb::PerturbationSpec {
        drops: parse("drop", &drops)?,
        faults: parse("fault", &faults)?,
        fault_rates: parse("fault rate", &fault_rates)?,
        seed,
        mono,
        depth_shift: match depth_shift {
            Some(s) => Some(parse("depth shift", &[s])?.remove(0)),
            None => None,
        },
    };
    let mut command = vec!["homing.run".to_string(), sequence.display().to_string()];
    command.push(out_dir.display().to_string());
    let opts = homing::system::RunOptions {
        sequence,
        out: out_dir,
        config,
        perturb,
        eval,
        command,
        threaded,
        load_map,
        save_map,
        strict_input,
        controller,
        no_loop_closing,
        mcap_log,
        ..Default::default()
    };
    let summary = py.detach(|| homing::system::run(&opts)).map_err(py_err)?;
    to_py(py, &summary)
}

/// `homing eval`: an estimate against ground truth (ATE, RPE, coverage; with `run`, a run
/// folder's closures judged and each map's ATE). Returns what `homing eval --json` prints.
#[pyfunction]
#[pyo3(signature = (gt = None, est = None, *, run = None, align = "se3", rpe_delta = 1.0,
    rpe_unit = "s", all_pairs = false, max_dt = 0.02, sequence = None))]
#[allow(clippy::too_many_arguments)]
fn evaluate<'py>(
    py: Python<'py>,
    gt: Option<PathBuf>,
    est: Option<PathBuf>,
    run: Option<PathBuf>,
    align: &str,
    rpe_delta: f64,
    rpe_unit: &str,
    all_pairs: bool,
    max_dt: f64,
    sequence: Option<PathBuf>,
) -> PyResult<Bound<'py, PyAny>> {
    use homing::eval::{Alignment, RpeUnit};
    let align = match align {
        "se3" => Alignment::Se3,
        "sim3" => Alignment::Sim3,
        "none" => Alignment::None,
        a => {
            return Err(PyValueError::new_err(format!(
                "align {a:?}: use \"se3\" (RGB-D), \"sim3\" (monocular) or \"none\""
            )));
        }
    };
    let rpe_unit = match rpe_unit {
        "s" => RpeUnit::Seconds,
        "frames" => RpeUnit::Frames,
        u => {
            return Err(PyValueError::new_err(format!(
                "rpe_unit {u:?}: use \"s\" or \"frames\""
            )));
        }
    };
    let req = homing::eval::report::EvalRequest {
        gt,
        est,
        run,
        align,
        rpe_delta,
        rpe_unit,
        all_pairs,
        max_dt,
        sequence,
    };
    let report = py
        .detach(|| homing::eval::report::evaluate(&req))
        .map_err(py_err)?;
    to_py(py, &report)
}

/// Renders a synthetic scenario (desk, loop, aliasing, revisit, case-study) into a TUM folder
/// with ground truth, as `homing-datasets synth` does; returns the folders written.
#[pyfunction]
#[pyo3(signature = (scenario, out_dir, *, small = true, seed = 1, max_frames = None,
    clean = false))]
fn synth(
    py: Python<'_>,
    scenario: &str,
    out_dir: PathBuf,
    small: bool,
    seed: u64,
    max_frames: Option<usize>,
    clean: bool,
) -> PyResult<Vec<PathBuf>> {
    use homing_datasets::{scenarios, sensor::SensorOptions, writer};
    let Some(sc) = scenarios::build(scenario, seed) else {
        return Err(PyValueError::new_err(format!(
            "unknown scenario {scenario:?}; choose one of {}",
            scenarios::NAMES.join(", ")
        )));
    };
    let opts = writer::GenOptions {
        out: out_dir,
        small,
        seed,
        sensor: if clean {
            SensorOptions::clean()
        } else {
            SensorOptions::realistic()
        },
        max_frames,
    };
    let stats = py
        .detach(|| writer::generate(&sc, &opts))
        .map_err(|e| PyValueError::new_err(format!("generating {scenario}: {e:#}")))?;
    Ok(stats.dirs)
}

#[pymodule]
fn _homing(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<Camera>()?;
    m.add_class::<FrameResult>()?;
    m.add_class::<Slam>()?;
    m.add_class::<TumSequence>()?;
    m.add_function(wrap_pyfunction!(run, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(synth, m)?)?;
    Ok(())
}
