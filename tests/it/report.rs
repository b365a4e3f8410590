//! `homing report`: the HTML report of a run (sections, embedded PNGs that decode, nothing
//! outside the file), and clear errors on broken run folders.

use crate::common;
use base64::Engine as _;
use homing::io::perturb::PerturbationSpec;
use homing::outputs::report::{results_table, write_report};
use homing::system::{RunOptions, run};
use homing_datasets::scenarios;
use homing_datasets::sensor::SensorOptions;
use homing_datasets::writer::GenOptions;
use std::path::Path;

/// The embedded PNGs of a report, with the size their `<img>` tag claims.
fn embedded_pngs(html: &str) -> Vec<(Vec<u8>, u32, u32)> {
    let mut out = Vec::new();
    for tag in html.split("<img ").skip(1) {
        let tag = &tag[..tag.find('>').expect("closed tag")];
        let attr = |name: &str| -> &str {
            let k = format!("{name}=\"");
            let s = &tag[tag
                .find(&k)
                .unwrap_or_else(|| panic!("no {name} in {tag:.80}"))
                + k.len()..];
            &s[..s.find('"').unwrap()]
        };
        let src = attr("src");
        let data = src
            .strip_prefix("data:image/png;base64,")
            .unwrap_or_else(|| panic!("image not embedded as a PNG data URI: {src:.60}"));
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(data)
            .expect("valid base64");
        out.push((
            bytes,
            attr("width").parse().unwrap(),
            attr("height").parse().unwrap(),
        ));
    }
    out
}

#[test]
fn report_of_a_small_synthetic_run() {
    let tmp = tempfile::tempdir().unwrap();
    let sc = scenarios::build("desk", 1).unwrap();
    common::generate(
        &sc,
        &GenOptions {
            out: tmp.path().join("desk"),
            small: true,
            seed: 1,
            sensor: SensorOptions::realistic(),
            max_frames: Some(60),
        },
    );
    let out = tmp.path().join("run");
    // A kidnapping, so the state timeline has more than one state.
    let summary = run(&RunOptions {
        sequence: tmp.path().join("desk"),
        out: out.clone(),
        eval: true,
        perturb: PerturbationSpec {
            drops: vec!["30:40".parse().unwrap()],
            ..Default::default()
        },
        ..Default::default()
    })
    .unwrap();
    let table = results_table(&summary);
    // The largest map leads the table (its ATE and share of the frames).
    assert!(
        table.trim_start().starts_with("largest map"),
        "largest map does not lead\n{table}"
    );
    for k in [
        "ATE RMSE",
        "RPE 1 s",
        "coverage",
        "maps",
        "keyframes",
        "closures",
        "final state",
        "fps",
    ] {
        assert!(table.contains(k), "{k} missing from\n{table}");
    }

    // Library: default path OUTDIR/report.html, ground truth found through summary.json.
    let path = write_report(&out, None, None).unwrap();
    assert_eq!(path, out.join("report.html"));
    let html = std::fs::read_to_string(&path).unwrap();
    for id in ["run", "trajectory", "error", "timing", "map", "closures"] {
        assert!(
            html.contains(&format!("<section id=\"{id}\">")),
            "section {id} missing"
        );
    }
    for text in [
        "ATE (Se3)",
        "RPE (1 s)",
        "coverage",
        "median ms",
        "Idle",
        "Mapping",
        "groundtruth.txt",
    ] {
        assert!(html.contains(text), "{text:?} missing from the report");
    }
    // Self-contained: nothing fetched from elsewhere.
    assert!(!html.contains("http://") && !html.contains("https://"));
    assert_eq!(
        html.matches(" src=\"").count(),
        html.matches(" src=\"data:").count()
    );
    let pngs = embedded_pngs(&html);
    assert_eq!(
        pngs.len(),
        4,
        "top view, error + states, timing, timing histograms"
    );
    for (bytes, w, h) in &pngs {
        let img = image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
            .expect("a PNG that decodes");
        assert_eq!((img.width(), img.height()), (*w, *h));
        assert!(*w >= 800 && *h >= 150, "{w}x{h}");
    }

    // Command line: --out elsewhere, --gt given explicitly.
    let other = tmp.path().join("elsewhere.html");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_homing"))
        .arg("report")
        .arg(&out)
        .arg("--gt")
        .arg(tmp.path().join("desk/groundtruth.txt"))
        .arg("--out")
        .arg(&other)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("elsewhere.html"));
    assert!(
        std::fs::read_to_string(&other)
            .unwrap()
            .contains("<section id=\"timing\">")
    );
}

/// A minimal run folder written by hand (no SLAM needed for the error cases).
fn fake_run(dir: &Path, states_rows: &str) {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(
        dir.join("summary.json"),
        r#"{"frames": 3, "keyframes": 1, "maps": 1, "final_state": "Final"}"#,
    )
    .unwrap();
    std::fs::write(
        dir.join("trajectory.txt"),
        "1.000000 0 0 0 0 0 0 1\n1.100000 0.1 0 0 0 0 0 1\n1.200000 0.2 0 0 0 0 0 1\n",
    )
    .unwrap();
    std::fs::write(dir.join("keyframes.txt"), "1.000000 0 0 0 0 0 0 1 0\n").unwrap();
    std::fs::write(
        dir.join("states.csv"),
        format!(
            "frame,timestamp,state,from,trigger,initialized,able_to_track,able_to_localize,consistent_map,map\n{states_rows}"
        ),
    )
    .unwrap();
    std::fs::write(
        dir.join("closures.csv"),
        "frame,kind,t_query,t_match,map_query,map_match,matched_kf,tx,ty,tz,qx,qy,qz,qw,inliers,verdict,pool\n",
    )
    .unwrap();
}

#[test]
fn report_errors_name_the_file_and_line() {
    let tmp = tempfile::tempdir().unwrap();
    let good = "0,1.000000,Idle,Init,initialized,1,0,0,1,\n1,1.100000,Mapping,Idle,able_to_track,1,1,0,1,0\n2,1.200000,Mapping,,,1,1,0,1,0\n";
    // A well-formed hand-made folder gives a report (no ground truth: no evaluation).
    let ok = tmp.path().join("ok");
    fake_run(&ok, good);
    let html = std::fs::read_to_string(write_report(&ok, None, None).unwrap()).unwrap();
    assert!(html.contains("<section id=\"error\">") && html.contains("no ground truth"));

    // Line 3 of states.csv has a bad frame number.
    let bad = tmp.path().join("bad");
    fake_run(
        &bad,
        "0,1.000000,Idle,Init,initialized,1,0,0,1,\nx,1.100000,Mapping,Idle,able_to_track,1,1,0,1,0\n",
    );
    let e = write_report(&bad, None, None).unwrap_err().to_string();
    assert!(e.contains("states.csv:3:") && e.contains("frame"), "{e}");
    assert!(!bad.join("report.html").exists());

    // A missing file is named.
    std::fs::remove_file(ok.join("closures.csv")).unwrap();
    let e = write_report(&ok, None, None).unwrap_err().to_string();
    assert!(e.contains("closures.csv"), "{e}");

    // Malformed summary.json: file and line.
    let js = tmp.path().join("js");
    fake_run(&js, good);
    std::fs::write(
        js.join("summary.json"),
        "{\n  \"frames\": 3,\n  \"maps\": ]\n}\n",
    )
    .unwrap();
    let e = write_report(&js, None, None).unwrap_err().to_string();
    assert!(e.contains("summary.json:3:"), "{e}");

    // keyframes.txt with a missing column: file and line.
    let kf = tmp.path().join("kf");
    fake_run(&kf, good);
    std::fs::write(kf.join("keyframes.txt"), "# header\n1.0 0 0 0 0 0 0 1\n").unwrap();
    let e = write_report(&kf, None, None).unwrap_err().to_string();
    assert!(e.contains("keyframes.txt:2:"), "{e}");

    // timing.csv with a bad duration: file and line.
    let tc = tmp.path().join("tc");
    fake_run(&tc, good);
    std::fs::write(tc.join("timing.csv"), "stage,ms\nframe,12.5\nframe,-3\n").unwrap();
    let e = write_report(&tc, None, None).unwrap_err().to_string();
    assert!(e.contains("timing.csv:3:"), "{e}");

    // A --gt that does not exist is named.
    let g = tmp.path().join("g");
    fake_run(&g, good);
    let e = write_report(&g, Some(&tmp.path().join("nope.txt")), None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("nope.txt"), "{e}");
}
