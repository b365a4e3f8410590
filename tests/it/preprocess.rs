//! ORB extraction: count, spread over the image, undistortion, depth lookup.

use homing::components::preprocess::{Preprocessor, hamming};
use homing::config::{CameraConfig, OrbConfig};
use homing::io::tum::{DepthImage, Frame};
use rand::{Rng, SeedableRng};

/// A 640x480 image of random rectangles: corners everywhere, one very busy corner region.
fn textured_frame(seed: u64) -> Frame {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut img = image::RgbImage::from_pixel(640, 480, image::Rgb([128, 128, 128]));
    for _ in 0..900 {
        let (w, h) = (rng.random_range(4..40), rng.random_range(4..40));
        let (x0, y0) = (rng.random_range(0..640 - w), rng.random_range(0..480 - h));
        let v: u8 = rng.random();
        for y in y0..y0 + h {
            for x in x0..x0 + w {
                img.put_pixel(x, y, image::Rgb([v, v, v]));
            }
        }
    }
    // A dense checkerboard in the top-left corner would take every feature without distribution.
    for y in 0..120 {
        for x in 0..160 {
            let v = if (x / 4 + y / 4) % 2 == 0 { 0 } else { 255 };
            img.put_pixel(x, y, image::Rgb([v, v, v]));
        }
    }
    let mut depth = DepthImage::new(640, 480);
    for (i, d) in depth.data.iter_mut().enumerate() {
        *d = 1.0 + (i % 640) as f32 / 640.0;
    }
    Frame {
        index: 0,
        t: 0.0,
        rgb: img,
        depth: Some(depth),
    }
}

fn camera(distorted: bool) -> CameraConfig {
    let mut c = homing::config::builtin_camera("freiburg1").unwrap();
    if !distorted {
        (c.k1, c.k2, c.p1, c.p2, c.k3) = (0.0, 0.0, 0.0, 0.0, 0.0);
    }
    c
}

#[test]
fn orb_count_and_spread() {
    let mut pre = Preprocessor::new(&camera(false), &OrbConfig::default()).unwrap();
    let m = pre.process(&textured_frame(1)).unwrap();
    assert!(m.len() >= 800 && m.len() <= 1000, "{} keypoints", m.len());
    assert_eq!(m.descriptors.len(), m.len());
    let mut cells = [0usize; 16];
    for k in &m.keypoints {
        cells[(k.un.y / 120.0) as usize * 4 + (k.un.x / 160.0) as usize] += 1;
    }
    // Every cell of a 4x4 grid has features, and the busy corner does not take them all.
    assert!(cells.iter().all(|&c| c >= 15), "{cells:?}");
    assert!(cells[0] < m.len() / 4, "{cells:?}");
    assert!(
        m.keypoints.iter().any(|k| k.octave >= 4),
        "no features on coarse levels"
    );
    // Depth under each keypoint: the test depth ramps with x.
    for (k, &d) in m.keypoints.iter().zip(&m.depth) {
        let expect = 1.0 + k.raw.x.round() as f32 / 640.0;
        assert!((d - expect).abs() < 1e-6);
    }
    // Deterministic.
    let m2 = pre.process(&textured_frame(1)).unwrap();
    assert_eq!(m.descriptors, m2.descriptors);
    assert!(hamming(&m.descriptors[0], &m.descriptors[0]) == 0);
}

#[test]
fn undistortion_moves_keypoints_as_the_model_says() {
    let cam = camera(true);
    let mut pre = Preprocessor::new(&cam, &OrbConfig::default()).unwrap();
    let m = pre.process(&textured_frame(2)).unwrap();
    // Re-distort each undistorted point with the radial-tangential model: must give the raw one.
    for k in m.keypoints.iter().take(200) {
        let x = (k.un.x - cam.cx) / cam.fx;
        let y = (k.un.y - cam.cy) / cam.fy;
        let r2 = x * x + y * y;
        let radial = 1.0 + cam.k1 * r2 + cam.k2 * r2 * r2 + cam.k3 * r2 * r2 * r2;
        let xd = x * radial + 2.0 * cam.p1 * x * y + cam.p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + cam.p1 * (r2 + 2.0 * y * y) + 2.0 * cam.p2 * x * y;
        let (u, v) = (cam.fx * xd + cam.cx, cam.fy * yd + cam.cy);
        assert!(
            (u - k.raw.x).abs() < 0.05 && (v - k.raw.y).abs() < 0.05,
            "{u},{v} vs {:?}",
            k.raw
        );
    }
}

/// Sparse, non-overlapping rectangles of distinct grey levels: every corner of the image is a
/// rectangle corner, and corners are far enough apart to pair each keypoint with one.
/// Returns the frame and the corners in pixel-centre coordinates (a rectangle covering pixels
/// x0..x1 has its left edge at x0 − 0.5).
fn sparse_rectangles(seed: u64) -> (Frame, Vec<(f64, f64)>) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut img = image::RgbImage::from_pixel(640, 480, image::Rgb([128, 128, 128]));
    let mut taken: Vec<(u32, u32, u32, u32)> = Vec::new();
    let mut corners = Vec::new();
    // Placement by rejection: 16 rectangles fit easily, and the attempts are bounded.
    for _ in 0..10_000 {
        if taken.len() == 16 {
            break;
        }
        let (w, h) = (rng.random_range(30..70), rng.random_range(30..70));
        let (x0, y0) = (rng.random_range(40..600 - w), rng.random_range(40..440 - h));
        // At least 30 px between rectangles, so that no two corners are close.
        if taken
            .iter()
            .any(|&(a, b, c, d)| x0 < c + 30 && a < x0 + w + 30 && y0 < d + 30 && b < y0 + h + 30)
        {
            continue;
        }
        taken.push((x0, y0, x0 + w, y0 + h));
        let v: u8 = if rng.random::<bool>() {
            rng.random_range(0..60)
        } else {
            rng.random_range(196..=255)
        };
        for y in y0..y0 + h {
            for x in x0..x0 + w {
                img.put_pixel(x, y, image::Rgb([v, v, v]));
            }
        }
        let (l, r) = (x0 as f64 - 0.5, (x0 + w) as f64 - 0.5);
        let (t, b) = (y0 as f64 - 0.5, (y0 + h) as f64 - 0.5);
        corners.extend([(l, t), (r, t), (l, b), (r, b)]);
    }
    let frame = Frame {
        index: 0,
        t: 0.0,
        rgb: img,
        depth: None,
    };
    (frame, corners)
}

/// With `orb.pixel_centre_levels` a keypoint found on a coarse pyramid level is reported where
/// it is in the full image: OpenCV's resize aligns pixel centres, so level pixel `x` is image
/// pixel `(x + 0.5)·s − 0.5`, not `x·s` (ORB-SLAM's and the default, which puts level-7 points
/// 1.3 px up and left of where they are). FAST's own offset from a corner is up to half a
/// level pixel either way depending on the corner, so single levels are noisy; over all coarse
/// levels and many corners of every orientation it averages out, and the mean signed offset to
/// the true corners must be near zero (−0.7 px in x and y with `x·s`).
#[test]
fn coarse_level_keypoints_are_where_the_corners_are() {
    let (centred, n) = mean_corner_offset(true);
    assert!(
        centred.0.abs() < 0.25 && centred.1.abs() < 0.25,
        "coarse keypoints are {centred:?} px off their corners on average ({n})"
    );
    // ORB-SLAM's convention, the default: the offset is there.
    let (default, _) = mean_corner_offset(false);
    assert!(
        default.0 < -0.5 && default.1 < -0.5,
        "x·s keypoints are {default:?} px off their corners on average"
    );
}

/// Mean signed offset (x, y) of keypoints of levels 2 and up from the nearest rectangle corner,
/// and how many keypoints it averages.
fn mean_corner_offset(pixel_centre_levels: bool) -> ((f64, f64), usize) {
    let cfg = OrbConfig {
        pixel_centre_levels,
        ..OrbConfig::default()
    };
    let mut pre = Preprocessor::new(&camera(false), &cfg).unwrap();
    let (mut sx, mut sy, mut n) = (0.0f64, 0.0f64, 0usize);
    for seed in 0..12 {
        let (frame, corners) = sparse_rectangles(seed);
        let m = pre.process(&frame).unwrap();
        for k in m.keypoints.iter().filter(|k| k.octave >= 2) {
            let s = pre.scales[k.octave as usize];
            let (dx, dy) = corners
                .iter()
                .map(|&(cx, cy)| (k.raw.x - cx, k.raw.y - cy))
                .min_by(|a, b| (a.0.hypot(a.1)).total_cmp(&b.0.hypot(b.1)))
                .unwrap();
            if dx.hypot(dy) <= 3.0 * s {
                sx += dx;
                sy += dy;
                n += 1;
            }
        }
    }
    assert!(n > 2000, "only {n} coarse keypoints near corners");
    ((sx / n as f64, sy / n as f64), n)
}
