//! Helpers shared by the integration tests: tiny TUM folders written on the spot.
#![allow(dead_code)]

use homing::io::tum::{
    DepthImage, StampedPose, save_depth, save_png, write_list, write_trajectory,
};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use std::path::{Path, PathBuf};

pub const W: u32 = 64;
pub const H: u32 = 48;

/// Writes a camera.toml for the tiny W×H test images.
pub fn write_camera(dir: &Path) {
    std::fs::write(
        dir.join("camera.toml"),
        format!(
            "[camera]\nname = \"test\"\nfx = 50.0\nfy = 50.0\ncx = 32.0\ncy = 24.0\nwidth = {W}\nheight = {H}\n"
        ),
    )
    .unwrap();
}

/// A valid n-frame TUM folder (30 Hz, depth stamps 5 ms late, ground truth at 100 Hz).
pub fn tum_folder(root: &Path, name: &str, n: usize) -> PathBuf {
    let dir = root.join(name);
    std::fs::create_dir_all(dir.join("rgb")).unwrap();
    std::fs::create_dir_all(dir.join("depth")).unwrap();
    write_camera(&dir);
    let (mut rgb, mut depth) = (Vec::new(), Vec::new());
    for i in 0..n {
        let t = 1000.0 + i as f64 / 30.0;
        let img = image::RgbImage::from_fn(W, H, |x, y| {
            image::Rgb([(x * 4) as u8, (y * 5) as u8, i as u8])
        });
        let f = format!("rgb/{t:.6}.png");
        save_png(&dir.join(&f), &image::DynamicImage::ImageRgb8(img)).unwrap();
        rgb.push((t, f));
        let mut d = DepthImage::new(W, H);
        d.data.iter_mut().for_each(|v| *v = 1.5);
        let td = t + 0.005;
        let f = format!("depth/{td:.6}.png");
        save_depth(&dir.join(&f), &d, 5000.0).unwrap();
        depth.push((td, f));
    }
    write_list(&dir.join("rgb.txt"), &rgb, "colour images").unwrap();
    write_list(&dir.join("depth.txt"), &depth, "depth images").unwrap();
    let gt: Vec<StampedPose> = (0..(n as f64 / 30.0 * 100.0) as usize + 10)
        .map(|k| {
            let t = 1000.0 - 0.05 + k as f64 / 100.0;
            StampedPose {
                t,
                pose: Isometry3::from_parts(
                    Translation3::new(0.1 * t.sin(), 0.05 * k as f64 / 100.0, 0.0),
                    UnitQuaternion::from_euler_angles(0.0, 0.01 * k as f64, 0.0),
                ),
            }
        })
        .collect();
    write_trajectory(&dir.join("groundtruth.txt"), &gt, "test ground truth").unwrap();
    dir
}

/// Runs the homing binary, returning (success, stdout, stderr).
pub fn homing<S: AsRef<std::ffi::OsStr>>(args: &[S]) -> (bool, String, String) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_homing"))
        .args(args)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Asserts that an error message is clear: no panic, and it names `needle` (file and/or line).
pub fn assert_clear_error(ok: bool, stderr: &str, needle: &str) {
    assert!(!ok, "expected failure, stderr: {stderr}");
    assert!(!stderr.contains("panicked"), "panicked: {stderr}");
    assert!(stderr.contains("error:"), "no error line: {stderr}");
    assert!(
        stderr.contains(needle),
        "error does not name '{needle}': {stderr}"
    );
}

/// [`homing_datasets::writer::generate`] on a thread pool of its own. The generator renders on
/// rayon; in the global pool, the case study's long generation (about 4,000 frames) kept every
/// other test's generation waiting behind it (one test took 289 s instead of 4).
pub fn generate(
    sc: &homing_datasets::scenarios::Scenario,
    opts: &homing_datasets::writer::GenOptions,
) -> homing_datasets::writer::Stats {
    let threads = std::thread::available_parallelism().map_or(2, |n| n.get());
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(|| homing_datasets::writer::generate(sc, opts))
        .unwrap()
}

/// Generates synthetic scenario `name` (seed 1, realistic sensor) at full size (640×480,
/// every frame).
pub fn synth_full(name: &str, dir: &Path) {
    use homing_datasets::{scenarios, sensor::SensorOptions, writer};
    let sc = scenarios::build(name, 1).unwrap();
    let opts = writer::GenOptions {
        out: dir.to_path_buf(),
        small: false,
        seed: 1,
        sensor: SensorOptions::realistic(),
        max_frames: None,
    };
    generate(&sc, &opts);
}

/// Synthetic scenario `name` (seed 1, realistic sensor) at its small size (320×240, the
/// scenario's own stride), generated once per test process and shared by every test that runs
/// on it: runs only read a sequence, and generating `loop` or `aliasing` costs 15–19 s of CPU
/// each time (twenty generations were about a fifth of the suite's CPU time).
pub fn small(name: &str) -> PathBuf {
    use homing_datasets::{scenarios, sensor::SensorOptions, writer};
    use std::collections::BTreeMap;
    use std::sync::{Arc, Mutex, OnceLock};
    static CACHE: Mutex<BTreeMap<String, Arc<OnceLock<PathBuf>>>> = Mutex::new(BTreeMap::new());
    let cell = CACHE
        .lock()
        .unwrap()
        .entry(name.to_string())
        .or_default()
        .clone();
    cell.get_or_init(|| {
        let dir = sequences_root().join(name);
        let opts = writer::GenOptions {
            out: dir.clone(),
            small: true,
            seed: 1,
            sensor: SensorOptions::realistic(),
            max_frames: None,
        };
        generate(&scenarios::build(name, 1).unwrap(), &opts);
        dir
    })
    .clone()
}

/// This process's folder for [`small`]'s sequences, under cargo's scratch folder for
/// integration tests. Folders left by earlier test processes that are no longer running
/// (Linux: no /proc/PID) are removed first, so at most the last run's sequences stay.
fn sequences_root() -> &'static Path {
    static ROOT: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    ROOT.get_or_init(|| {
        let base = Path::new(env!("CARGO_TARGET_TMPDIR")).join("it-sequences");
        for entry in std::fs::read_dir(&base).into_iter().flatten().flatten() {
            let running = entry
                .file_name()
                .to_str()
                .and_then(|p| p.parse::<u32>().ok())
                .is_some_and(|pid| Path::new("/proc").join(pid.to_string()).exists());
            if !running {
                let _ = std::fs::remove_dir_all(entry.path());
            }
        }
        let root = base.join(std::process::id().to_string());
        let _ = std::fs::remove_dir_all(&root);
        std::fs::create_dir_all(&root).unwrap();
        root
    })
}

/// A run (with evaluation) of synthetic scenario `name` at its small size, under `perturb`.
pub struct SmallRun {
    /// Keeps the outputs alive.
    pub tmp: tempfile::TempDir,
    pub seq: PathBuf,
    pub out: PathBuf,
    pub summary: homing::outputs::Summary,
}

/// Scenario `name` small ([`small`]) run under `perturb`, with evaluation.
pub fn run_small(name: &str, perturb: homing::io::perturb::PerturbationSpec) -> SmallRun {
    run_small_with_config(name, perturb, None)
}

/// [`run_small`] with `config` (TOML text) as the run's `--config`.
pub fn run_small_with_config(
    name: &str,
    perturb: homing::io::perturb::PerturbationSpec,
    config: Option<&str>,
) -> SmallRun {
    let tmp = tempfile::tempdir().unwrap();
    let seq = small(name);
    let out = tmp.path().join("run");
    let config = config.map(|text| {
        let path = tmp.path().join("config.toml");
        std::fs::write(&path, text).unwrap();
        path
    });
    let summary = homing::system::run(&homing::system::RunOptions {
        sequence: seq.clone(),
        out: out.clone(),
        config,
        perturb,
        eval: true,
        ..Default::default()
    })
    .unwrap();
    SmallRun {
        tmp,
        seq,
        out,
        summary,
    }
}

/// A small generated `desk` sequence of `frames` frames in `dir`.
pub fn generated_desk(dir: &Path, frames: usize) -> PathBuf {
    use homing_datasets::{scenarios, sensor::SensorOptions, writer};
    let seq = dir.join("desk");
    generate(
        &scenarios::build("desk", 1).unwrap(),
        &writer::GenOptions {
            out: seq.clone(),
            small: true,
            seed: 1,
            sensor: SensorOptions::realistic(),
            max_frames: Some(frames),
        },
    );
    seq
}

/// The two runs' outputs are byte for byte the same, over at least `min_poses` poses.
pub fn same_outputs(a: &Path, b: &Path, min_poses: usize) {
    for f in [
        "trajectory.txt",
        "states.csv",
        "keyframes.txt",
        "closures.csv",
    ] {
        let (x, y) = (
            std::fs::read(a.join(f)).unwrap(),
            std::fs::read(b.join(f)).unwrap(),
        );
        assert!(x == y, "{f} differs");
    }
    let poses = std::fs::read_to_string(b.join("trajectory.txt")).unwrap();
    let n = poses.lines().filter(|l| !l.starts_with('#')).count();
    assert!(
        n >= min_poses,
        "only {n} poses: the comparison would prove little"
    );
}
