//! `homing eval` against values computed once with evo 1.38.1 (commands in expected.json, made
//! by tests/fixtures/eval/make_fixtures.py). The requirement is agreement to 1e-4 m; we check 1e-6.

use crate::common;
use homing::eval::{self, Alignment, RpeUnit};
use homing::io::tum::read_trajectory;
use serde_json::Value;
use std::path::{Path, PathBuf};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/eval")
        .join(name)
}

fn check(stats: &eval::Stats, expected: &Value, what: &str, tol: f64) {
    for (k, v) in [
        ("rmse", stats.rmse),
        ("mean", stats.mean),
        ("median", stats.median),
        ("std", stats.std),
        ("min", stats.min),
        ("max", stats.max),
    ] {
        let e = expected[k].as_f64().unwrap();
        assert!((v - e).abs() <= tol, "{what} {k}: homing {v} vs evo {e}");
    }
}

#[test]
fn ate_and_rpe_agree_with_evo() {
    let expected: Value =
        serde_json::from_str(&std::fs::read_to_string(fixture("expected.json")).unwrap()).unwrap();
    let gt = read_trajectory(&fixture("groundtruth.txt")).unwrap();
    let cases = expected["cases"].as_array().unwrap();
    assert_eq!(cases.len(), 3);
    for case in cases {
        let name = case["estimate"].as_str().unwrap();
        let est = read_trajectory(&fixture(name)).unwrap();
        for (align, key) in [(Alignment::Se3, "ate_se3"), (Alignment::Sim3, "ate_sim3")] {
            let assoc = eval::associate_and_align(&gt, &est, align, 0.02).unwrap();
            let ate = eval::ate(&assoc, align);
            check(&ate.stats, &case[key], &format!("{name} {key}"), 1e-6);
        }
        // evo_rpe without -a: no alignment (RPE is invariant to a rigid one anyway).
        let assoc = eval::associate_and_align(&gt, &est, Alignment::None, 0.02).unwrap();
        for delta in [1.0, 30.0] {
            let r = eval::rpe(&assoc, delta, RpeUnit::Frames, false).unwrap();
            check(
                &r.trans,
                &case[format!("rpe_trans_f{delta}")],
                &format!("{name} rpe trans {delta}"),
                1e-6,
            );
            check(
                &r.rot_deg,
                &case[format!("rpe_rot_f{delta}")],
                &format!("{name} rpe rot {delta}"),
                1e-5,
            );
        }
    }
}

#[test]
fn exact_copy_gives_zero_and_sim3_recovers_scale() {
    let gt = read_trajectory(&fixture("groundtruth.txt")).unwrap();
    let exact = read_trajectory(&fixture("est_exact.txt")).unwrap();
    let assoc = eval::associate_and_align(&gt, &exact, Alignment::Se3, 0.02).unwrap();
    assert!(eval::ate(&assoc, Alignment::Se3).stats.rmse < 1e-6);
    // An exact copy scaled by 0.5 and moved rigidly: Sim3 alignment must find scale 2 exactly
    // and zero error; SE3 alignment cannot explain it.
    let motion = nalgebra::Isometry3::new(
        nalgebra::Vector3::new(0.3, -1.0, 2.0),
        nalgebra::Vector3::new(0.2, 0.5, -0.4),
    );
    let half: Vec<_> = gt
        .iter()
        .map(|p| {
            let mut q = motion * p.pose;
            q.translation.vector =
                motion.rotation * (0.5 * p.pose.translation.vector) + motion.translation.vector;
            homing::io::tum::StampedPose { t: p.t, pose: q }
        })
        .collect();
    let assoc = eval::associate_and_align(&gt, &half, Alignment::Sim3, 0.02).unwrap();
    assert!(
        (assoc.alignment.scale - 2.0).abs() < 1e-9,
        "{}",
        assoc.alignment.scale
    );
    assert!(eval::ate(&assoc, Alignment::Sim3).stats.max < 1e-9);
    let se3 = eval::associate_and_align(&gt, &half, Alignment::Se3, 0.02).unwrap();
    assert!(eval::ate(&se3, Alignment::Se3).stats.rmse > 0.01);
    // The noisy half-scale fixture: the noise biases the scale estimate slightly low.
    let noisy = read_trajectory(&fixture("est_scale0.5.txt")).unwrap();
    let assoc = eval::associate_and_align(&gt, &noisy, Alignment::Sim3, 0.02).unwrap();
    assert!(
        (assoc.alignment.scale - 2.0).abs() < 0.03,
        "{}",
        assoc.alignment.scale
    );
    // Ground truth against itself: 0 in every alignment.
    for align in [Alignment::Se3, Alignment::Sim3, Alignment::None] {
        let assoc = eval::associate_and_align(&gt, &gt, align, 0.02).unwrap();
        assert!(eval::ate(&assoc, align).stats.max < 1e-9);
        let r = eval::rpe(&assoc, 1.0, RpeUnit::Seconds, false).unwrap();
        assert!(r.trans.max < 1e-9 && r.rot_deg.max < 1e-6);
    }
}

#[test]
fn cli_reports_injected_noise_and_writes_plot() {
    let dir = tempfile::tempdir().unwrap();
    let plot = dir.path().join("ate.png");
    let (ok, out, err) = common::homing(&[
        "eval",
        "--gt",
        fixture("groundtruth.txt").to_str().unwrap(),
        "--est",
        fixture("est_noise1cm.txt").to_str().unwrap(),
        "--json",
        "--plot",
        plot.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let v: Value = serde_json::from_str(&out).unwrap();
    let rmse = v["ate"]["stats"]["rmse"].as_f64().unwrap();
    // 1 cm Gaussian noise per axis: 3-D RMSE ≈ √3 cm.
    assert!((rmse - 0.01 * 3f64.sqrt()).abs() < 0.002, "{rmse}");
    let img = image::open(&plot).unwrap();
    assert_eq!((img.width(), img.height()), (1400, 600));
}
