//! vocab-tools: descriptor extraction, HBST construction, place-recognition evaluation and
//! timing of the loop detector's descriptor index. See vocab_tools/README.md.

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use homing::components::loop_detector::LoopDetectorParams;
use homing::components::loop_detector::vocabulary::Vocabulary;
use homing::config::Config;
use homing::io::atomic_write;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use vocab_tools::bench::{self, BenchOptions, Source, WorldParams};
use vocab_tools::eval::{self, EvalOptions};
use vocab_tools::{DescriptorFile, extract, tree};

#[derive(Parser)]
#[command(
    name = "vocab-tools",
    version,
    about = "Descriptor-tree (HBST) tools for homing's loop detector: extract ORB descriptors, \
             build a tree, evaluate place recognition, time the index",
    after_help = "Example (TUM fr1_xyz):\n  \
        vocab-tools extract --sequence data/rgbd_dataset_freiburg1_xyz --out fr1_xyz.desc\n  \
        vocab-tools build --descriptors fr1_xyz.desc\n  \
        vocab-tools eval --descriptors fr1_xyz.desc --gt data/rgbd_dataset_freiburg1_xyz/groundtruth.txt\n  \
        vocab-tools bench --sizes 100,1000,5000"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Extract the ORB descriptors of a TUM sequence (as `homing run` computes them) to a file.
    ///
    /// The camera is chosen as `homing run` does: the config's [camera], else camera.toml in
    /// the sequence folder, else freiburg1/2/3 from the folder name.
    ///
    /// Example: vocab-tools extract --sequence data/rgbd_dataset_freiburg1_xyz --every 2 --out fr1_xyz.desc
    Extract {
        /// TUM RGB-D folder (rgb.txt, depth.txt, rgb/, depth/).
        #[arg(long)]
        sequence: PathBuf,
        /// Config file (TOML): camera, [orb] and [sequence] settings.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Keep every N-th frame (starting with the first).
        #[arg(long, default_value_t = 1)]
        every: usize,
        /// Output descriptor file (written atomically).
        #[arg(long)]
        out: PathBuf,
    },
    /// Build an HBST from all descriptors of a file (frame by frame) and print its shape:
    /// depth, leaves, leaf size distribution, split balance, build time.
    ///
    /// Example: vocab-tools build --descriptors fr1_xyz.desc --max-leaf-size 50
    Build {
        /// Descriptor file from `vocab-tools extract`.
        #[arg(long)]
        descriptors: PathBuf,
        #[command(flatten)]
        tree: TreeArgs,
        /// Also write the statistics as JSON to this file.
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// Place-recognition precision/recall against ground truth, HBST vs brute force.
    ///
    /// Every frame is a keyframe in sequence order: it queries the frames stored so far except
    /// the last --min-gap ones, then is stored. Its answer is the best-scoring candidate of the
    /// loop detector (same voting for both indices). A true match: cameras within
    /// --max-distance-m and --max-angle-deg. Prints precision/recall at the configured
    /// min_score/min_matches and over a score sweep, the share of brute-force descriptor
    /// matches the HBST finds, and query time against the number of stored images.
    ///
    /// Example: vocab-tools eval --descriptors fr1_xyz.desc --gt data/rgbd_dataset_freiburg1_xyz/groundtruth.txt --min-gap 30
    Eval {
        /// Descriptor file from `vocab-tools extract`.
        #[arg(long)]
        descriptors: PathBuf,
        /// Ground truth, TUM format (timestamp tx ty tz qx qy qz qw).
        #[arg(long)]
        gt: PathBuf,
        /// Candidates must be at least this many frames (of the file) older than the query.
        #[arg(long, default_value_t = 30)]
        min_gap: usize,
        /// Same place: camera centres at most this far apart (metres) ...
        #[arg(long, default_value_t = 0.5)]
        max_distance_m: f64,
        /// ... and orientations at most this far apart (degrees).
        #[arg(long, default_value_t = 30.0)]
        max_angle_deg: f64,
        /// Largest time difference between a frame and its ground-truth pose (seconds).
        #[arg(long, default_value_t = 0.02)]
        max_dt: f64,
        /// Score thresholds of the sweep (comma-separated); default 0 .. 0.4.
        #[arg(long, value_delimiter = ',')]
        thresholds: Option<Vec<f64>>,
        /// Bins of the query-time table.
        #[arg(long, default_value_t = 6)]
        time_bins: usize,
        /// Skip brute force (it is quadratic in the number of frames).
        #[arg(long)]
        no_brute_force: bool,
        /// Bag-of-words vocabulary to evaluate too ("built-in": the one homing ships).
        #[arg(long)]
        vocabulary: Option<PathBuf>,
        #[command(flatten)]
        tree: TreeArgs,
        /// Also write the report (with every query's answers) as JSON to this file.
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// Train a bag-of-words vocabulary (k-majority tree, TF-IDF) on generic photos.
    ///
    /// ORB features are extracted from every JPEG/PNG under the given folders exactly as
    /// homing extracts them (config's [orb]); never train on a sequence you evaluate on.
    ///
    /// Example: vocab-tools train --images imagenet-sample-images --images BSDS500/images --out vocab/orb_k10_l5.voc
    Train {
        /// Folder (searched recursively) or file of training images; repeat for several.
        #[arg(long, required = true)]
        images: Vec<PathBuf>,
        /// Config file (TOML) whose [orb] section sets the feature extraction.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Branching factor of the tree.
        #[arg(long, default_value_t = 10)]
        k: u32,
        /// Levels of the tree (words: up to k^levels).
        #[arg(long, default_value_t = 5)]
        levels: u32,
        /// Seed of the k-means++ seeding.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Output vocabulary file (written atomically).
        #[arg(long)]
        out: PathBuf,
    },
    /// Time HBST query + insert (+ voting) per keyframe at several tree sizes.
    ///
    /// Without --descriptors a deterministic synthetic world is used (biased bits, noisy
    /// re-observations of landmarks, loops); with it the file's frames are cycled (repeats
    /// with 1-4 flipped bits per descriptor).
    ///
    /// Example: vocab-tools bench --sizes 100,1000,5000 --per-keyframe 1000 --seed 1
    Bench {
        /// Keyframe counts to time at (comma-separated).
        #[arg(long, value_delimiter = ',', default_value = "100,1000,5000")]
        sizes: Vec<usize>,
        /// Keyframes timed at each size.
        #[arg(long, default_value_t = 50)]
        probes: usize,
        /// Descriptors per synthetic keyframe.
        #[arg(long, default_value_t = 1000)]
        per_keyframe: usize,
        /// Seed of the synthetic world and of the noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Use real descriptors from this file instead of the synthetic world.
        #[arg(long)]
        descriptors: Option<PathBuf>,
        #[command(flatten)]
        tree: TreeArgs,
        /// Also write the report as JSON to this file.
        #[arg(long)]
        json: Option<PathBuf>,
    },
}

/// The loop detector's parameters: the config's [loop_closing] (defaults without a config),
/// with the HBST parameters overridable.
#[derive(Args)]
struct TreeArgs {
    /// Config file (TOML) whose [loop_closing] section sets the HBST and voting parameters.
    #[arg(long)]
    config: Option<PathBuf>,
    /// HBST: a leaf with more descriptors splits (config: hbst_max_leaf_size).
    #[arg(long)]
    max_leaf_size: Option<usize>,
    /// HBST: largest Hamming distance of a match (config: hbst_max_distance).
    #[arg(long)]
    max_distance: Option<u32>,
    /// HBST: largest |0.5 - set fraction| of a split bit (config: hbst_max_split_imbalance).
    #[arg(long)]
    max_split_imbalance: Option<f64>,
    /// HBST: a query also scans the leaves its path reaches with up to this many split bits
    /// flipped (config: hbst_search_flips; 0 = one descent).
    #[arg(long)]
    search_flips: Option<u32>,
}

impl TreeArgs {
    /// Detector parameters and the temporal window.
    fn params(&self) -> Result<(LoopDetectorParams, usize)> {
        let cfg = match &self.config {
            Some(p) => Config::load(p)?,
            None => Config::default(),
        };
        let mut p = LoopDetectorParams::from_config(&cfg.loop_closing);
        if let Some(v) = self.max_leaf_size {
            if v == 0 {
                bail!("--max-leaf-size must be at least 1");
            }
            p.hbst.max_leaf_size = v;
        }
        if let Some(v) = self.max_distance {
            if v > 256 {
                bail!("--max-distance must be at most 256");
            }
            p.hbst.max_distance = v;
        }
        if let Some(v) = self.max_split_imbalance {
            if !(0.0..=0.5).contains(&v) {
                bail!("--max-split-imbalance must be within [0, 0.5]");
            }
            p.hbst.max_split_imbalance = v;
        }
        if let Some(v) = self.search_flips {
            if v > 3 {
                bail!("--search-flips must be at most 3");
            }
            p.hbst.search_flips = v;
        }
        Ok((p, cfg.loop_closing.temporal_window as usize))
    }
}

fn write_json(path: &Path, value: &impl serde::Serialize) -> Result<()> {
    let text = serde_json::to_string_pretty(value)?;
    atomic_write(path, text.as_bytes())?;
    eprintln!("wrote {}", path.display());
    Ok(())
}

fn read_descriptors(path: &Path) -> Result<DescriptorFile> {
    let f = DescriptorFile::read(path)?;
    eprintln!(
        "{}: {} frames, {} descriptors",
        path.display(),
        f.frames.len(),
        f.n_descriptors()
    );
    Ok(f)
}

fn progress(what: &'static str) -> impl FnMut(usize, usize) {
    move |done, total| {
        if done.is_multiple_of(50) || done == total {
            eprint!("\r{what}: {done}/{total}");
            if done == total {
                eprintln!();
            }
            let _ = std::io::stderr().flush();
        }
    }
}

fn main() {
    let cli = Cli::parse();
    if let Err(e) = run(cli.cmd) {
        eprintln!("vocab-tools: error: {e:#}");
        std::process::exit(1);
    }
}

fn run(cmd: Cmd) -> Result<()> {
    match cmd {
        Cmd::Train {
            images,
            config,
            k,
            levels,
            seed,
            out,
        } => {
            let cfg = match &config {
                Some(p) => Config::load(p)?,
                None => Config::default(),
            };
            let files = vocab_tools::train::image_files(&images)?;
            if files.is_empty() {
                bail!("no JPEG or PNG images under the given --images");
            }
            let (v, s) =
                vocab_tools::train::train(&files, &cfg.orb, k, levels, seed, progress("train"))?;
            v.save(&out)?;
            for (f, e) in &s.skipped {
                eprintln!("skipped {}: {e}", f.display());
            }
            println!(
                "{} images ({} skipped), {} descriptors, {} words (k {k}, {levels} levels); \
                 extraction {:.1} s, training {:.1} s; wrote {}",
                s.images,
                s.skipped.len(),
                s.descriptors,
                s.words,
                s.seconds_extract,
                s.seconds_train,
                out.display()
            );
        }
        Cmd::Extract {
            sequence,
            config,
            every,
            out,
        } => {
            let (file, s) =
                extract::extract(&sequence, config.as_deref(), every, progress("extract"))?;
            file.write(&out)?;
            println!("{}", s.camera);
            println!(
                "{} of {} frames, {} descriptors (per frame min {}, mean {:.0}, max {}), \
                 median {:.1} ms per frame; wrote {}",
                s.frames,
                s.sequence_frames,
                s.descriptors,
                s.min_per_frame,
                s.descriptors as f64 / s.frames.max(1) as f64,
                s.max_per_frame,
                s.median_ms_per_frame,
                out.display()
            );
        }
        Cmd::Build {
            descriptors,
            tree: t,
            json,
        } => {
            let (p, _) = t.params()?;
            let file = read_descriptors(&descriptors)?;
            let (_, report) = tree::build(&file, p.hbst);
            print!("{}", report.to_text());
            if let Some(j) = json {
                write_json(&j, &report)?;
            }
        }
        Cmd::Eval {
            descriptors,
            gt,
            min_gap,
            max_distance_m,
            max_angle_deg,
            max_dt,
            thresholds,
            time_bins,
            no_brute_force,
            vocabulary,
            tree: t,
            json,
        } => {
            let vocabulary = match vocabulary {
                None => None,
                Some(p) if p.as_os_str() == "built-in" => Some(Vocabulary::built_in()),
                Some(p) => Some(Vocabulary::load(&p)?),
            }
            .map(std::sync::Arc::new);
            let (p, _) = t.params()?;
            let file = read_descriptors(&descriptors)?;
            let (frames, skipped) =
                eval::attach_ground_truth(&file, &gt, max_dt).with_context(|| {
                    format!("pairing {} with {}", descriptors.display(), gt.display())
                })?;
            if skipped > 0 {
                eprintln!(
                    "{skipped} frames have no ground truth within {max_dt} s and are left out"
                );
            }
            let o = EvalOptions {
                detector: p,
                min_gap,
                max_distance_m,
                max_angle_deg,
                thresholds: thresholds.unwrap_or_else(|| eval::DEFAULT_THRESHOLDS.to_vec()),
                time_bins,
                brute_force: !no_brute_force,
                vocabulary,
            };
            let report = eval::evaluate(&frames, &o);
            println!(
                "HBST max_leaf_size {}, max_distance {}; voting: ratio {}, self-similarity filter {}",
                p.hbst.max_leaf_size,
                p.hbst.max_distance,
                p.ambiguity_ratio,
                if p.self_similarity.is_some() {
                    "on"
                } else {
                    "off"
                }
            );
            print!("{}", report.to_text());
            if let Some(j) = json {
                write_json(&j, &report)?;
            }
        }
        Cmd::Bench {
            sizes,
            probes,
            per_keyframe,
            seed,
            descriptors,
            tree: t,
            json,
        } => {
            let (p, temporal_window) = t.params()?;
            if sizes.is_empty() || probes == 0 {
                bail!("--sizes and --probes must not be empty / zero");
            }
            let (mut source, name) = match &descriptors {
                Some(path) => {
                    let file = read_descriptors(path)?;
                    let s = Source::real(&file)
                        .with_context(|| format!("{} holds no descriptors", path.display()))?;
                    (s, format!("real descriptors from {}", path.display()))
                }
                None => {
                    if per_keyframe < 10 {
                        bail!("--per-keyframe must be at least 10");
                    }
                    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(
                        seed ^ 0x5eed,
                    );
                    let w = WorldParams::new(per_keyframe);
                    (
                        Source::synthetic(w, &mut rng),
                        format!(
                            "synthetic world ({per_keyframe} descriptors per keyframe, {} new \
                             landmarks per keyframe, {} visible, {:.0}% clutter, 0-{} flipped bits)",
                            w.stride,
                            w.window,
                            100.0 * w.clutter,
                            w.max_flips
                        ),
                    )
                }
            };
            let o = BenchOptions {
                sizes,
                probes,
                seed,
                detector: p,
                temporal_window,
            };
            let report = bench::run(&mut source, &name, &o, progress("bench keyframes"));
            print!("{}", report.to_text());
            if let Some(j) = json {
                write_json(&j, &report)?;
            }
        }
    }
    Ok(())
}
