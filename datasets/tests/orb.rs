//! ORB (as in homing's front end: 1000 features, 8 levels, scale 1.2, FAST 20/7) must find
//! plenty of well-spread keypoints on rendered frames.

use homing_datasets::render::{Intrinsics, render};
use homing_datasets::scenarios;
use homing_datasets::sensor::{SensorOptions, colour_image};
use opencv::core::{Mat, Vector};
use opencv::features2d::{ORB, ORB_ScoreType};
use opencv::prelude::*;

fn orb_stats(img: &image::RgbImage) -> (usize, [[usize; 4]; 4]) {
    let (w, h) = (img.width() as i32, img.height() as i32);
    let gray = image::DynamicImage::ImageRgb8(img.clone()).to_luma8();
    let flat = Mat::from_slice(gray.as_raw()).unwrap();
    let mat = flat.reshape(1, h).unwrap().try_clone().unwrap();
    let mut orb = ORB::create(1000, 1.2, 8, 31, 0, 2, ORB_ScoreType::HARRIS_SCORE, 31, 20).unwrap();
    let mut kps = Vector::new();
    orb.detect(&mat, &mut kps, &Mat::default()).unwrap();
    let mut grid = [[0usize; 4]; 4];
    for kp in kps.iter() {
        let p = kp.pt();
        let gx = ((p.x / w as f32) * 4.0).clamp(0.0, 3.0) as usize;
        let gy = ((p.y / h as f32) * 4.0).clamp(0.0, 3.0) as usize;
        grid[gy][gx] += 1;
    }
    (kps.len(), grid)
}

#[test]
fn orb_finds_many_well_spread_keypoints() {
    let k = Intrinsics::kinect(640, 480);
    for (name, frac) in [("desk", 0.5), ("case-study", 0.02), ("case-study", 0.3)] {
        let sc = scenarios::build(name, 1).unwrap();
        let leg = &sc.sessions[0].legs[0];
        let t = leg.start() + frac * (leg.end() - leg.start());
        let r = render(&sc.scene, &k, &leg.pose(t));
        let img = colour_image(&r, 1.0, &SensorOptions::realistic(), 1, 0);
        let (n, grid) = orb_stats(&img);
        eprintln!("{name} t={t:.1}: {n} keypoints, grid {grid:?}");
        assert!(n >= 500, "{name}: only {n} keypoints");
        for row in grid {
            for c in row {
                assert!(c > 0, "{name}: empty grid cell: {grid:?}");
            }
        }
    }
}

/// Survey of a written folder: `HOMING_ORB_DIR=... cargo test -p homing-datasets --test orb
/// -- --ignored --nocapture` prints ORB counts of every 15th frame (lit frames should all be
/// well covered; only dark steps may be empty).
#[test]
#[ignore]
fn orb_survey_of_folder() {
    let Ok(dir) = std::env::var("HOMING_ORB_DIR") else {
        return;
    };
    let dir = std::path::PathBuf::from(dir);
    let list = homing::io::tum::read_list(&dir.join("rgb.txt")).unwrap();
    let mut worst = (usize::MAX, 0);
    for (i, e) in list.iter().enumerate().step_by(15) {
        let img = image::open(dir.join(&e.file)).unwrap().to_rgb8();
        let (n, grid) = orb_stats(&img);
        let empty = grid.iter().flatten().filter(|&&c| c == 0).count();
        println!("frame {i}: {n} keypoints, {empty} empty cells of 16");
        if n < worst.0 {
            worst = (n, i);
        }
    }
    println!("fewest: {} keypoints at frame {}", worst.0, worst.1);
}
