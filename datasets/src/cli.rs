//! Command line of `homing-datasets`.

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::{Args, Parser, Subcommand};

use crate::scenarios::{self, NAMES};
use crate::sensor::SensorOptions;
use crate::sheet::write_contact_sheet;
use crate::writer::{GenOptions, generate};

#[derive(Debug, Parser)]
#[command(
    name = "homing-datasets",
    version,
    about = "Synthetic TUM RGB-D sequences for homing"
)]
pub struct Cli {
    #[command(subcommand)]
    pub cmd: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Render a scenario into a TUM RGB-D folder (case-study: DIR/session1 and DIR/session2).
    Synth(SynthArgs),
    /// Grid of every n-th frame of a TUM folder, labelled with frame index and step.
    ContactSheet {
        /// TUM folder (with rgb.txt).
        dir: PathBuf,
        #[arg(long, default_value_t = 30)]
        every: usize,
        #[arg(long)]
        out: PathBuf,
        /// Thumbnail width in pixels.
        #[arg(long, default_value_t = 160)]
        thumb: u32,
        #[arg(long, default_value_t = 8)]
        columns: usize,
    },
    /// List the scenarios.
    List,
}

#[derive(Debug, Args)]
pub struct SynthArgs {
    /// desk, loop, aliasing, aliasing-return, revisit, case-study, turn-in-place or turn-in-place-reference
    /// (the same walk without the full turns).
    #[arg(long)]
    pub scenario: String,
    #[arg(long)]
    pub out: PathBuf,
    /// 320x240 and fewer frames (every n-th frame; fps lowered accordingly).
    #[arg(long)]
    pub small: bool,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// All noise off: exact depth (quantised by the PNG), no holes, no image noise, equal stamps.
    #[arg(long)]
    pub clean: bool,
    #[arg(long)]
    pub no_depth_noise: bool,
    #[arg(long)]
    pub no_depth_holes: bool,
    #[arg(long)]
    pub no_image_noise: bool,
    /// Depth and colour stamps equal (no association needed).
    #[arg(long)]
    pub no_time_offset: bool,
    /// Keep the lights on in the scenario's dark stretches.
    #[arg(long)]
    pub no_darkness: bool,
    /// Average five renders over a 20 ms exposure (5x slower).
    #[arg(long)]
    pub motion_blur: bool,
    /// Maximum valid depth in metres.
    #[arg(long)]
    pub max_range: Option<f64>,
    /// Render only the first N frames of each session.
    #[arg(long)]
    pub max_frames: Option<usize>,
}

impl SynthArgs {
    pub fn sensor(&self) -> anyhow::Result<SensorOptions> {
        let mut s = if self.clean {
            SensorOptions::clean()
        } else {
            SensorOptions::realistic()
        };
        s.depth_noise &= !self.no_depth_noise;
        s.depth_holes &= !self.no_depth_holes;
        s.image_noise &= !self.no_image_noise;
        s.time_offset &= !self.no_time_offset;
        s.darkness &= !self.no_darkness;
        s.motion_blur |= self.motion_blur;
        if let Some(r) = self.max_range {
            if !(r.is_finite() && r > 0.0 && r <= 13.0) {
                bail!("--max-range must be in (0, 13] m (16-bit depth at 5000/m), got {r}");
            }
            s.max_range = r;
        }
        Ok(s)
    }
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.cmd {
        Command::List => {
            for n in NAMES {
                let sc = scenarios::build(n, 1).expect("listed scenarios exist");
                println!("{n:12} {}", sc.description);
            }
        }
        Command::Synth(a) => {
            let Some(sc) = scenarios::build(&a.scenario, a.seed) else {
                bail!(
                    "unknown scenario {:?}; choose one of {}",
                    a.scenario,
                    NAMES.join(", ")
                );
            };
            let opts = GenOptions {
                out: a.out.clone(),
                small: a.small,
                seed: a.seed,
                sensor: a.sensor()?,
                max_frames: a.max_frames,
            };
            let stats =
                generate(&sc, &opts).with_context(|| format!("generating {}", a.scenario))?;
            let (w, h) = opts.size();
            for d in &stats.dirs {
                println!("wrote {}", d.display());
            }
            println!(
                "{} frames at {w}x{h} in {:.1} s: {:.1} frames/s",
                stats.frames,
                stats.seconds,
                stats.fps()
            );
        }
        Command::ContactSheet {
            dir,
            every,
            out,
            thumb,
            columns,
        } => {
            write_contact_sheet(&dir, every, thumb, columns, &out)
                .with_context(|| format!("contact sheet of {}", dir.display()))?;
            println!("wrote {}", out.display());
        }
    }
    Ok(())
}
