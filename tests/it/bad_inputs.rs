//! Bad inputs get a clear error naming the file (and line), never a panic.

use crate::common;
use common::{assert_clear_error, homing, tum_folder};
use std::fs;

fn run_on(dir: &std::path::Path, out: &std::path::Path) -> (bool, String, String) {
    run_with(dir, out, &[])
}

/// [`run_on`] with `--strict-input`: an unreadable frame ends the run.
fn run_strict(dir: &std::path::Path, out: &std::path::Path) -> (bool, String, String) {
    run_with(dir, out, &["--strict-input"])
}

fn run_with(
    dir: &std::path::Path,
    out: &std::path::Path,
    extra: &[&str],
) -> (bool, String, String) {
    let mut args = vec![
        "run",
        "--sequence",
        dir.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    homing(&args)
}

#[test]
fn truncated_png() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tum_folder(tmp.path(), "seq", 5);
    let victim = fs::read_dir(dir.join("rgb"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .min()
        .unwrap();
    let bytes = fs::read(&victim).unwrap();
    fs::write(&victim, &bytes[..bytes.len() / 2]).unwrap();
    let out = tmp.path().join("out");
    let (ok, _, err) = run_strict(&dir, &out);
    assert_clear_error(ok, &err, victim.file_name().unwrap().to_str().unwrap());
    // Results up to the bad frame are still written, with the error recorded.
    let summary = fs::read_to_string(out.join("summary.json")).unwrap();
    assert!(summary.contains("\"error\""), "{summary}");
}

#[test]
fn eight_bit_depth() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tum_folder(tmp.path(), "seq", 3);
    let victim = fs::read_dir(dir.join("depth"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .min()
        .unwrap();
    image::GrayImage::new(common::W, common::H)
        .save(&victim)
        .unwrap();
    let (ok, _, err) = run_strict(&dir, &tmp.path().join("out"));
    assert_clear_error(ok, &err, "16-bit");
    assert!(
        err.contains(victim.file_name().unwrap().to_str().unwrap()),
        "{err}"
    );
}

#[test]
fn wrong_image_size() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tum_folder(tmp.path(), "seq", 3);
    let victim = fs::read_dir(dir.join("rgb"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .min()
        .unwrap();
    image::RgbImage::new(10, 10).save(&victim).unwrap();
    let (ok, _, err) = run_strict(&dir, &tmp.path().join("out"));
    assert_clear_error(ok, &err, "10x10");
}

#[test]
fn missing_image() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tum_folder(tmp.path(), "seq", 3);
    let victim = fs::read_dir(dir.join("rgb"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .max()
        .unwrap();
    fs::remove_file(&victim).unwrap();
    let (ok, _, err) = run_strict(&dir, &tmp.path().join("out"));
    assert_clear_error(ok, &err, victim.file_name().unwrap().to_str().unwrap());
}

/// Without `--strict-input` a frame that cannot be read is a failed measurement: a sequence
/// with a truncated colour PNG, a missing one and an 8-bit depth image runs to its end, a
/// warning names each file, summary.json counts and lists them, and the evaluation does not
/// expect them posed. With `--strict-input` the first of them ends the run.
#[test]
fn unreadable_frames_are_failed_measurements() {
    let tmp = tempfile::tempdir().unwrap();
    // A copy of small `desk` (the shared one must stay intact).
    let dir = tmp.path().join("desk");
    copy_dir(&common::small("desk"), &dir);
    let sorted = |sub: &str| {
        let mut v: Vec<_> = fs::read_dir(dir.join(sub))
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        v.sort();
        v
    };
    let (rgb, depth) = (sorted("rgb"), sorted("depth"));
    let n = rgb.len() as u64;
    let truncated = &rgb[3];
    let bytes = fs::read(truncated).unwrap();
    fs::write(truncated, &bytes[..bytes.len() / 2]).unwrap();
    let missing = &rgb[6];
    fs::remove_file(missing).unwrap();
    let eight_bit = &depth[9];
    image::GrayImage::new(common::W, common::H)
        .save(eight_bit)
        .unwrap();
    let name = |p: &std::path::Path| p.file_name().unwrap().to_str().unwrap().to_string();

    let out = tmp.path().join("out");
    let (ok, _, err) = run_with(&dir, &out, &["--eval"]);
    assert!(ok, "{err}");
    assert!(!err.contains("panicked"), "{err}");
    for p in [truncated, missing, eight_bit] {
        assert!(
            err.contains(&name(p)),
            "no warning names {}: {err}",
            name(p)
        );
    }
    let s: serde_json::Value =
        serde_json::from_str(&fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(s["frames"], n, "{s}");
    assert_eq!(s["frames_unreadable"], 3, "{s}");
    let listed: Vec<u64> = s["unreadable_frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|u| u["frame"].as_u64().unwrap())
        .collect();
    assert_eq!(listed, [3, 6, 9]);
    assert!(s.get("error").is_none(), "{s}");
    // Tracking goes on across them, and coverage does not count them.
    assert_eq!(s["maps"], 1, "{s}");
    assert!(s["frames_with_pose"].as_u64().unwrap() >= n - 3, "{s}");
    let ev = &s["evaluation"];
    assert_eq!(ev["delivered_frames_judged"], n - 3, "{ev}");
    assert_eq!(ev["largest_map_accurate_coverage"], 1.0, "{ev}");

    let (ok, _, err) = run_strict(&dir, &tmp.path().join("strict"));
    assert_clear_error(ok, &err, &name(truncated));
}

/// Rewrites line `n` (1-based, counting comment lines) of a text file.
fn edit_line(path: &std::path::Path, n: usize, f: impl Fn(&str) -> String) {
    let text = fs::read_to_string(path).unwrap();
    let lines: Vec<String> = text
        .lines()
        .enumerate()
        .map(|(i, l)| if i + 1 == n { f(l) } else { l.to_string() })
        .collect();
    fs::write(path, lines.join("\n") + "\n").unwrap();
}

/// A broken-input case: its name, how it rewrites a line, and the message expected.
type LineCase = (&'static str, Box<dyn Fn(&str) -> String>, &'static str);

#[test]
fn list_file_errors_name_file_and_line() {
    // rgb.txt: 2 comment lines, then frames from line 3.
    let cases: [LineCase; 4] = [
        (
            "missing column",
            Box::new(|l: &str| l.split_whitespace().next().unwrap().to_string()),
            "expected 2 columns",
        ),
        (
            "NaN",
            Box::new(|l: &str| format!("NaN {}", l.split_whitespace().nth(1).unwrap())),
            "not a finite number",
        ),
        (
            "duplicated",
            Box::new(|_: &str| "1000.000000 rgb/x.png".to_string()),
            "duplicated",
        ),
        (
            "unsorted",
            Box::new(|_: &str| "999.0 rgb/x.png".to_string()),
            "not increasing",
        ),
    ];
    for (what, f, needle) in cases {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tum_folder(tmp.path(), "seq", 4);
        edit_line(&dir.join("rgb.txt"), 4, f);
        let (ok, _, err) = run_on(&dir, &tmp.path().join("out"));
        assert_clear_error(ok, &err, "rgb.txt:4:");
        assert!(err.contains(needle), "{what}: {err}");
    }
}

#[test]
fn trajectory_errors_name_file_and_line() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tum_folder(tmp.path(), "seq", 4);
    let gt = dir.join("groundtruth.txt");
    for (f, needle) in [
        (
            Box::new(|l: &str| l.rsplit_once(' ').unwrap().0.to_string())
                as Box<dyn Fn(&str) -> String>,
            "expected 8 columns",
        ),
        (
            Box::new(|l: &str| {
                l.replacen(" ", " nan ", 1)
                    .rsplit_once(' ')
                    .unwrap()
                    .0
                    .to_string()
            }),
            "not a finite number",
        ),
        (
            Box::new(|_: &str| "1000.0 0 0 0 0 0 0 2".to_string()),
            "norm",
        ),
    ] {
        let est = tmp.path().join("est.txt");
        fs::copy(&gt, &est).unwrap();
        edit_line(&est, 5, f);
        let (ok, _, err) = homing(&[
            "eval",
            "--gt",
            gt.to_str().unwrap(),
            "--est",
            est.to_str().unwrap(),
        ]);
        assert_clear_error(ok, &err, "est.txt:5:");
        assert!(err.contains(needle), "{err}");
    }
}

#[test]
fn empty_and_missing_folders() {
    let tmp = tempfile::tempdir().unwrap();
    let empty = tmp.path().join("empty");
    fs::create_dir(&empty).unwrap();
    common::write_camera(&empty);
    let (ok, _, err) = run_on(&empty, &tmp.path().join("o1"));
    assert_clear_error(ok, &err, "no rgb.txt");
    // Lists present but holding only comments.
    fs::write(empty.join("rgb.txt"), "# nothing\n").unwrap();
    fs::write(empty.join("depth.txt"), "# nothing\n").unwrap();
    let (ok, _, err) = run_on(&empty, &tmp.path().join("o2"));
    assert_clear_error(ok, &err, "holds no frames");
    let (ok, _, err) = run_on(&tmp.path().join("nope"), &tmp.path().join("o3"));
    assert_clear_error(ok, &err, "nope");
}

#[test]
fn unknown_config_key_and_bad_values() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tum_folder(tmp.path(), "seq", 2);
    let cfg = tmp.path().join("bad.toml");
    fs::write(&cfg, "[tracker]\nmin_inliers = 30\nmin_inlers = 3\n").unwrap();
    let (ok, _, err) = homing(&[
        "run",
        "--sequence",
        dir.to_str().unwrap(),
        "--out",
        tmp.path().join("o").to_str().unwrap(),
        "--config",
        cfg.to_str().unwrap(),
    ]);
    assert_clear_error(ok, &err, "bad.toml:3:");
    assert!(err.contains("min_inlers"), "{err}");
    fs::write(
        &cfg,
        "[camera]\nfx = -5.0\nfy = 1.0\ncx = 1.0\ncy = 1.0\nwidth = 64\nheight = 48\n",
    )
    .unwrap();
    let (ok, _, err) = homing(&["config", "--check", cfg.to_str().unwrap()]);
    assert_clear_error(ok, &err, "bad.toml:2: camera.fx");
    fs::write(&cfg, "[camera\nfx = 1\n").unwrap();
    let (ok, _, err) = homing(&["config", "--check", cfg.to_str().unwrap()]);
    assert_clear_error(ok, &err, "bad.toml:1:");
}

#[test]
fn bad_perturbation_arguments() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tum_folder(tmp.path(), "seq", 5);
    let out = tmp.path().join("o");
    for (args, needle) in [
        (vec!["--drop", "3:1"], "selects no frame"),
        (vec!["--fault", "black@99"], "past the end"),
        (vec!["--fault", "purple@1"], "unknown fault kind"),
        (vec!["--fault-rate", "noise:2"], "probability"),
    ] {
        let mut a = vec![
            "run",
            "--sequence",
            dir.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        a.extend(args);
        let (ok, _, err) = homing(&a);
        assert!(
            !ok && !err.contains("panicked") && err.contains(needle),
            "{err}"
        );
    }
}

#[test]
fn camera_cannot_be_guessed() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tum_folder(tmp.path(), "seq", 2);
    fs::remove_file(dir.join("camera.toml")).unwrap();
    let (ok, _, err) = run_on(&dir, &tmp.path().join("o"));
    assert_clear_error(ok, &err, "cannot tell the camera");
}

fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    fs::create_dir_all(to).unwrap();
    for e in fs::read_dir(from).unwrap() {
        let p = e.unwrap().path();
        let dest = to.join(p.file_name().unwrap());
        if p.is_dir() {
            copy_dir(&p, &dest);
        } else {
            fs::copy(&p, &dest).unwrap();
        }
    }
}
