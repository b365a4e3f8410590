//! The streaming API (`homing::slam::Slam`): frames given one at a time give the program's
//! outputs byte for byte (deterministic mode), RGB-D and monocular; a stop part-way leads to
//! Final with every output; wrong input is an error, not a panic.

use crate::common;

use homing::config::{CameraConfig, Config, resolve_camera};
use homing::io::tum::{FrameSource, TumSequence};
use homing::outputs::RunOutputs;
use homing::slam::Slam;
use std::path::Path;

/// The config, camera and frames a run of `seq` uses, as `homing run [--mono]` opens them.
fn open(seq: &Path, mono: bool) -> (Config, CameraConfig, TumSequence) {
    let mut config = Config::default();
    config.sequence.mono = mono;
    let (camera, _) = resolve_camera(&config, None, seq).unwrap();
    let frames = TumSequence::open(
        seq,
        camera.width,
        camera.height,
        camera.depth_scale,
        config.sequence.max_association_dt,
        mono,
    )
    .unwrap();
    (config, camera, frames)
}

/// Runs `seq` through the API frame by frame and writes the run files into `out`.
fn run_api(
    seq: &Path,
    mono: bool,
    out: &Path,
    stop_after: Option<usize>,
) -> homing::slam::SlamOutput {
    let (config, camera, frames) = open(seq, mono);
    let mut slam = Slam::new(&config, &camera).unwrap();
    let mut tracked = 0;
    for i in 0..frames.len() {
        let f = frames.load(i).unwrap();
        let r = slam.track(f.t, f.rgb, f.depth).unwrap();
        assert_eq!(r.frame, i);
        tracked += r.pose_wc.is_some() as usize;
        // Without depth, the frames the initializer waited on are posed when their map starts.
        assert!(r.earlier_frames.iter().all(|&e| e < i));
        tracked += r.earlier_frames.len();
        assert_eq!(r.map.is_some(), r.pose_wc.is_some());
        if stop_after == Some(i + 1) {
            break;
        }
    }
    assert!(tracked > 0);
    // The trajectory so far is there between frames.
    assert_eq!(slam.trajectory().len(), tracked);
    let result = if stop_after.is_some() {
        slam.request_stop().unwrap()
    } else {
        slam.finish().unwrap()
    };
    let o = RunOutputs::create(out).unwrap();
    o.write_trajectory(&result.trajectory).unwrap();
    o.write_keyframes(&result.keyframes).unwrap();
    o.write_states(&result.states).unwrap();
    o.write_closures(&result.closures).unwrap();
    result
}

#[test]
fn the_api_gives_the_programs_outputs_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let seq = common::generated_desk(dir.path(), 90);
    for mono in [false, true] {
        let cli = dir.path().join(format!("cli-{mono}"));
        let mut args = vec![
            "run",
            "--sequence",
            seq.to_str().unwrap(),
            "--out",
            cli.to_str().unwrap(),
        ];
        if mono {
            args.push("--mono");
        }
        let (ok, _, stderr) = common::homing(&args);
        assert!(ok, "{stderr}");
        let api = dir.path().join(format!("api-{mono}"));
        let r = run_api(&seq, mono, &api, None);
        common::same_outputs(&cli, &api, 60);
        assert_eq!(r.final_state, "Final");
        assert!(
            r.trajectory.len() > 60,
            "mono {mono}: {} poses",
            r.trajectory.len()
        );
    }
}

#[test]
fn a_stop_part_way_leads_to_final_with_every_output() {
    let dir = tempfile::tempdir().unwrap();
    let seq = common::generated_desk(dir.path(), 60);
    let out = dir.path().join("stopped");
    let r = run_api(&seq, false, &out, Some(30));
    let last = r.states.last().unwrap();
    assert_eq!(last.state, "Final");
    assert_eq!(
        last.transition.as_ref().unwrap().trigger,
        homing::control::USER_STOP
    );
    assert!(last.frame <= 29);
    assert!(!r.trajectory.is_empty() && !r.keyframes.is_empty());
    assert!(r.trajectory_frames.iter().all(|&f| f < 30));
}

#[test]
fn wrong_input_is_an_error_not_a_panic() {
    let dir = tempfile::tempdir().unwrap();
    let seq = common::tum_folder(dir.path(), "tiny", 3);
    let config = Config::default();
    let (camera, _) = resolve_camera(&config, None, &seq).unwrap();
    let mut slam = Slam::new(&config, &camera).unwrap();
    let img = || image::RgbImage::new(common::W, common::H);
    let err = |r: homing::Result<_>| r.map(|_| ()).unwrap_err().to_string();
    let e = err(slam.track(1.0, image::RgbImage::new(10, 10), None));
    assert!(e.contains("10x10") && e.contains("64x48"), "{e}");
    let e = err(slam.track(1.0, img(), Some(homing::io::tum::DepthImage::new(8, 8))));
    assert!(e.contains("depth image is 8x8"), "{e}");
    slam.track(1.0, img(), None).unwrap();
    let e = err(slam.track(1.0, img(), None));
    assert!(e.contains("does not follow"), "{e}");
    let e = err(slam.track(f64::NAN, img(), None));
    assert!(e.contains("does not follow"), "{e}");
    slam.finish().unwrap();
    assert!(err(slam.track(2.0, img(), None)).contains("finished"));
    assert!(slam.finish().is_err());
}

#[test]
fn a_saved_atlas_loads_back_in_a_second_session_that_relocalizes_in_it() {
    let dir = tempfile::tempdir().unwrap();
    let seq = common::generated_desk(dir.path(), 60);
    let (config, camera, frames) = open(&seq, false);
    let atlas_path = dir.path().join("desk.atlas");
    let mut first = Slam::new(&config, &camera).unwrap();
    for i in 0..frames.len() {
        let f = frames.load(i).unwrap();
        first.track(f.t, f.rgb, f.depth).unwrap();
    }
    first.finish().unwrap();
    first.save_atlas(&atlas_path).unwrap();
    let saved_maps: Vec<_> = first.atlas().maps.keys().copied().collect();

    let atlas = homing::atlas::Atlas::load(
        &atlas_path,
        &homing::atlas::AtlasCamera::from(&camera),
        false,
    )
    .unwrap();
    let mut second = Slam::new(&config, &camera).unwrap().with_atlas(atlas);
    // The same place again (later stamps): the camera is found in the loaded map.
    let mut in_loaded = 0;
    for i in 0..20 {
        let f = frames.load(i).unwrap();
        let r = second.track(f.t + 100.0, f.rgb, f.depth).unwrap();
        if r.map.is_some_and(|m| saved_maps.contains(&m)) && r.state == "Localized" {
            in_loaded += 1;
        }
    }
    assert!(
        in_loaded >= 10,
        "Localized in the loaded map on {in_loaded} of 20 frames"
    );
}

#[test]
fn borrowed_buffers_track_as_images_do() {
    use homing::slam::DepthBuffer;
    let dir = tempfile::tempdir().unwrap();
    let seq = common::generated_desk(dir.path(), 30);
    let (config, camera, frames) = open(&seq, false);
    let mut a = Slam::new(&config, &camera).unwrap();
    let mut units = Slam::new(&config, &camera).unwrap();
    let mut metres = Slam::new(&config, &camera).unwrap();
    for (i, r) in frames.frames.iter().enumerate() {
        let f = frames.load(i).unwrap();
        let d = f.depth.clone().unwrap();
        // The sensor's own 16-bit image, as a driver would hand it over.
        let raw = image::open(r.depth.as_ref().unwrap())
            .unwrap()
            .into_luma16()
            .into_raw();
        let rgb = f.rgb.as_raw().clone();
        let ra = a.track(f.t, f.rgb, f.depth).unwrap();
        let ru = units
            .track_buffers(f.t, &rgb, Some(DepthBuffer::Units(&raw)))
            .unwrap();
        let rm = metres
            .track_buffers(f.t, &rgb, Some(DepthBuffer::Metres(&d.data)))
            .unwrap();
        assert_eq!(ra.pose_wc, ru.pose_wc, "frame {i}");
        assert_eq!(ra.pose_wc, rm.pose_wc, "frame {i}");
    }
    assert!(a.trajectory().len() > 20);
    let e = units
        .track_buffers(99.0, &[0u8; 12], None)
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(e.contains("colour buffer holds 12 bytes"), "{e}");
    let rgb = vec![0u8; (3 * camera.width * camera.height) as usize];
    let e = units
        .track_buffers(99.0, &rgb, Some(DepthBuffer::Units(&[0u16; 5])))
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(e.contains("depth buffer holds 5 values"), "{e}");
}
