//! A TUM RGB-D folder through the streaming API, frame by frame: the state timeline as it
//! happens, then the final trajectory in TUM format.
//!
//! ```sh
//! cargo run --release --example tum_rgbd -- data/rgbd_dataset_freiburg1_desk [--mono] > trajectory.txt
//! ```
//! Evaluate with `homing eval --gt DIR/groundtruth.txt --est trajectory.txt` (or `evo_ape tum`).

use homing::config::{Config, resolve_camera};
use homing::io::tum::{FrameSource, TumSequence};
use homing::slam::Slam;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let dir = std::path::PathBuf::from(
        args.next()
            .ok_or_else(|| anyhow::anyhow!("usage: tum_rgbd SEQUENCE_DIR [--mono]"))?,
    );
    let mono = args.next().as_deref() == Some("--mono");
    let mut config = Config::default();
    config.sequence.mono = mono;
    // The camera as `homing run` picks it: DIR/camera.toml, or TUM's from the folder name.
    let (camera, _) = resolve_camera(&config, None, &dir)?;
    let frames = TumSequence::open(
        &dir,
        camera.width,
        camera.height,
        camera.depth_scale,
        config.sequence.max_association_dt,
        mono,
    )?;
    let mut slam = Slam::new(&config, &camera)?;
    let mut state = String::new();
    for i in 0..frames.len() {
        let f = frames.load(i)?;
        let r = slam.track(f.t, f.rgb, f.depth)?;
        if r.state != state {
            eprintln!("frame {:5} t {:.3}: {}", r.frame, r.t, r.state);
            state = r.state;
        }
        for p in &r.pools_accepted {
            eprintln!("frame {:5}: closure pool {p} accepted", r.frame);
        }
    }
    let out = slam.finish()?;
    eprintln!(
        "{} of {} frames posed, {} keyframes, {} maps",
        out.trajectory.len(),
        frames.len(),
        out.keyframes.len(),
        slam.atlas().maps.len()
    );
    for p in &out.trajectory {
        let (t, q) = (p.pose.translation.vector, p.pose.rotation.coords);
        println!(
            "{:.6} {:.6} {:.6} {:.6} {:.6} {:.6} {:.6} {:.6}",
            p.t, t.x, t.y, t.z, q.x, q.y, q.z, q.w
        );
    }
    Ok(())
}
