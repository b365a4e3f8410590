//! `homing bench memory`: peak memory and wall time against the length of a run that revisits
//! the same place over and over.
//!
//! The sequence is played 1×, 4×, 16× … in a row (a TUM folder whose `associations.txt` lists
//! the same images again with shifted time stamps, nothing copied), each a child `homing run`
//! whose summary.json reports its peak resident memory. Localized keeps the keyframes bounded
//! on revisits; what Final keeps per frame is bounded per keyframe
//! (`mapping.final_frames_per_keyframe`), so memory should follow the map, not the length.

use crate::error::{Error, Result};
use crate::io::Sequence;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

pub struct Options {
    /// A TUM RGB-D folder (its own camera.toml, or `config`'s camera).
    pub sequence: PathBuf,
    /// How many times the sequence is played in a row, one run each.
    pub repeats: Vec<usize>,
    pub out: PathBuf,
    pub config: Option<PathBuf>,
    /// The homing binary (default: this one).
    pub exe: Option<PathBuf>,
    /// Reuse the runs a stopped (or earlier) benchmark with the same sequence, config and
    /// version finished in OUT (see `DONE_MARK`); only the others run.
    pub resume: bool,
}

/// Written into OUT/run-xN/ once that run finished: what it depended on, which `--resume`
/// compares. A run a user stop interrupted gets none.
const DONE_MARK: &str = "bench-done.txt";

/// One run of the benchmark.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Row {
    pub repeats: usize,
    pub frames: u64,
    pub keyframes: u64,
    pub maps: u64,
    pub peak_rss_mb: f64,
    pub wall_s: f64,
}

/// Runs the benchmark; writes OUT/memory.md and OUT/memory.json and returns the table.
pub fn memory(o: &Options) -> Result<String> {
    let seq = crate::system::open_run_sequence(&o.sequence, o.config.as_deref(), false)?;
    let Sequence::Tum(tum) = &seq else {
        return Err(Error::invalid("bench memory needs a TUM folder"));
    };
    let frames = &tum.frames;
    let (Some(first), Some(last)) = (frames.first(), frames.last()) else {
        return Err(Error::file(&o.sequence, "holds no frames"));
    };
    // One play lasts its span plus one mean frame interval.
    let step = (last.t - first.t) / (frames.len().max(2) - 1) as f64;
    let period = last.t - first.t + step;
    let exe = match &o.exe {
        Some(e) => e.clone(),
        None => std::env::current_exe().map_err(|e| Error::invalid(e.to_string()))?,
    };
    std::fs::create_dir_all(&o.out)
        .map_err(|e| Error::file(&o.out, format!("cannot create: {e}")))?;
    let mut rows = Vec::new();
    let mut stopped = Vec::new();
    for &r in &o.repeats {
        let dir = o.out.join(format!("sequence-x{r}"));
        std::fs::create_dir_all(&dir)
            .map_err(|e| Error::file(&dir, format!("cannot create: {e}")))?;
        let camera = o.sequence.join("camera.toml");
        if camera.exists() {
            std::fs::copy(&camera, dir.join("camera.toml"))
                .map_err(|e| Error::file(&camera, format!("cannot copy: {e}")))?;
        }
        let mut list = String::from("# t_rgb rgb t_depth depth (the sequence played again)\n");
        for k in 0..r {
            for f in frames {
                let Some(depth) = &f.depth else { continue };
                let t = f.t + k as f64 * period;
                let abs = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
                let _ = writeln!(
                    list,
                    "{t:.6} {} {t:.6} {}",
                    abs(&f.rgb).display(),
                    abs(depth).display()
                );
            }
        }
        crate::io::atomic_write(&dir.join("associations.txt"), list.as_bytes())?;
        let run_out = o.out.join(format!("run-x{r}"));
        let mut cmd = std::process::Command::new(&exe);
        cmd.args(["-q", "run", "--sequence"])
            .arg(&dir)
            .arg("--out")
            .arg(&run_out);
        if let Some(c) = &o.config {
            cmd.arg("--config").arg(c);
        }
        let config = super::config_text(o.config.as_deref());
        let identity = format!(
            "homing {}\nsequence {}\nplays {r}\nconfig\n{config}",
            env!("CARGO_PKG_VERSION"),
            o.sequence.display()
        );
        let mark = run_out.join(DONE_MARK);
        let finished = o.resume && std::fs::read_to_string(&mark).is_ok_and(|m| m == identity);
        if finished {
            tracing::info!("resumed: the {r}× run is finished");
        } else if crate::interrupt::stop_requested() {
            stopped.push(r);
            continue;
        } else {
            tracing::info!("bench memory: {r}× the sequence");
            let status = cmd
                .status()
                .map_err(|e| Error::invalid(format!("cannot start {}: {e}", exe.display())))?;
            // Ctrl-C reaches the child too: it stops, writes its outputs and exits 130; that
            // run is no measurement of its length.
            if status.code() == Some(crate::interrupt::EXIT_STATUS)
                || crate::interrupt::stop_requested()
            {
                stopped.push(r);
                continue;
            }
            if !status.success() {
                return Err(Error::invalid(format!(
                    "the {r}× run failed ({status}); see {}",
                    run_out.display()
                )));
            }
            crate::io::atomic_write(&mark, identity.as_bytes())?;
        }
        let path = run_out.join("summary.json");
        let text = crate::error::read_text(&path)?;
        let s: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| Error::parse(&path, e.line(), e.to_string()))?;
        let u = |k: &str| s[k].as_u64().unwrap_or(0);
        let row = Row {
            repeats: r,
            frames: u("frames"),
            keyframes: u("keyframes"),
            maps: u("maps"),
            peak_rss_mb: s["peak_rss_mb"].as_f64().unwrap_or(f64::NAN),
            wall_s: s["wall_time_s"].as_f64().unwrap_or(f64::NAN),
        };
        println!(
            "{r}×: {} frames, {} keyframes, {} maps, peak RSS {:.1} MB, {:.1} s",
            row.frames, row.keyframes, row.maps, row.peak_rss_mb, row.wall_s
        );
        rows.push(row);
    }
    let base = rows.first().map_or(f64::NAN, |r| r.peak_rss_mb);
    let mut md = format!(
        "# Memory against run length: {} played 1× and again\n\n| plays | frames | keyframes | maps | peak RSS | vs first | wall | ms/frame |\n|---|---|---|---|---|---|---|---|\n",
        o.sequence.display()
    );
    for r in &rows {
        let _ = writeln!(
            md,
            "| {}× | {} | {} | {} | {:.1} MB | {:.2}× | {:.1} s | {:.1} |",
            r.repeats,
            r.frames,
            r.keyframes,
            r.maps,
            r.peak_rss_mb,
            r.peak_rss_mb / base,
            r.wall_s,
            1e3 * r.wall_s / r.frames.max(1) as f64
        );
    }
    if !stopped.is_empty() {
        let plays: Vec<String> = stopped.iter().map(|r| format!("{r}×")).collect();
        let _ = writeln!(
            md,
            "\n**Stopped by the user:** the {} runs not finished; the same command with `--resume` runs only those.",
            plays.join(", ")
        );
    }
    crate::io::atomic_write(&o.out.join("memory.md"), md.as_bytes())?;
    let json = serde_json::to_vec_pretty(&rows).map_err(|e| Error::invalid(e.to_string()))?;
    crate::io::atomic_write(&o.out.join("memory.json"), &json)?;
    Ok(md)
}
