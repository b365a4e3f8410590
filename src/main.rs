//! The `homing` command line.

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use homing::config::{Config, ControllerKind};
use homing::eval::{self, Alignment, RpeUnit};
use homing::io::perturb::{DepthShift, DropSpec, FaultRate, FaultSpec, PerturbationSpec};
use homing::system::{RunOptions, run};
use std::path::PathBuf;
use tracing_subscriber::EnvFilter;

mod cli_progress;

#[derive(Parser)]
#[command(
    name = "homing",
    version,
    about = "Visual SLAM driven by an explicit SLAM state machine"
)]
struct Cli {
    /// More log output (-v: debug, -vv: trace).
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    /// Only warnings and errors.
    #[arg(short, long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run on a TUM RGB-D folder and write the run outputs.
    ///
    /// Example: homing run --sequence data/rgbd_dataset_freiburg1_xyz --out out/fr1_xyz --eval
    Run(Box<RunArgs>),
    /// Evaluate an estimated trajectory against ground truth (ATE, RPE, coverage).
    ///
    /// Example: homing eval --gt seq/groundtruth.txt --est out/trajectory.txt --plot ate.png
    Eval(EvalArgs),
    /// Write a self-contained HTML report of a run: trajectory vs ground truth, error over
    /// time with the state timeline, per-stage timing, map and closure statistics.
    ///
    /// Example: homing report out/fr1_xyz --out out/fr1_xyz/report.html
    Report {
        /// A `homing run` output folder.
        #[arg(value_name = "OUTDIR")]
        dir: PathBuf,
        /// Ground truth, TUM format (default: the run's sequence's groundtruth.txt, if any).
        #[arg(long)]
        gt: Option<PathBuf>,
        /// Where to write the report (default: OUTDIR/report.html).
        #[arg(long, value_name = "FILE.html")]
        out: Option<PathBuf>,
    },
    /// Benchmarks that print numbers (per-stage ms/frame, fps, ATE).
    ///
    /// Example: homing bench tracking --sequence data/rgbd_dataset_freiburg1_xyz --out out/bench
    #[command(subcommand)]
    Bench(BenchCmd),
    /// Print a modal controller's state machine as Graphviz DOT (the tables the run follows).
    ///
    /// Example: homing states --dot --controller ours --out ours.dot --png ours.png
    States {
        /// Write DOT (the only format so far; the flag is kept for clarity).
        #[arg(long)]
        dot: bool,
        /// Which machine.
        #[arg(long, value_enum, default_value = "ours")]
        controller: ControllerKind,
        /// Write the DOT here instead of standard output.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Also render a PNG with Graphviz's `dot` (when installed).
        #[arg(long)]
        png: Option<PathBuf>,
    },
    /// Convert between sequence formats.
    ///
    /// Example: homing convert tum-to-mcap data/rgbd_dataset_freiburg1_xyz fr1_xyz.mcap
    #[command(subcommand)]
    Convert(ConvertCmd),
    /// Print the default configuration, or check a config file and print it resolved.
    ///
    /// Example: homing config --check my.toml
    Config {
        /// A config file to validate.
        #[arg(long)]
        check: Option<PathBuf>,
    },
}

#[derive(Subcommand)]
enum ConvertCmd {
    /// Write a ROS 2 bag (MCAP, cdr) from a TUM folder: rgb8 images on
    /// /camera/rgb/image_color, 16UC1 depth on /camera/depth/image, CameraInfo on
    /// /camera/rgb/camera_info (when the camera is known), ground truth on /groundtruth (JSON).
    TumToMcap {
        /// TUM RGB-D folder.
        dir: PathBuf,
        /// The bag to write.
        out: PathBuf,
        /// Depth in millimetres (ROS's 16UC1 convention, rounded) instead of the TUM values
        /// with their scale in the channel metadata (lossless, read back exactly by homing).
        #[arg(long)]
        depth_mm: bool,
    },
}

#[derive(Subcommand)]
enum BenchCmd {
    /// Peak memory and wall time against run length: the sequence played 1×, 4×, 16× in a row
    /// (the same place over and over), one child run each; writes OUT/memory.md and .json.
    ///
    /// Example: homing bench memory --sequence data/small/revisit --repeats 1,4,16
    Memory {
        /// TUM RGB-D folder.
        #[arg(long)]
        sequence: PathBuf,
        /// Plays of the sequence, one run each.
        #[arg(long, value_delimiter = ',', default_value = "1,4,16")]
        repeats: Vec<usize>,
        /// Config file (TOML) for every run.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Output folder.
        #[arg(long, default_value = "out/bench-memory")]
        out: PathBuf,
        /// Reuse the runs that a stopped (Ctrl-C) or earlier benchmark with the same sequence
        /// and config finished in OUT; only the others run.
        #[arg(long)]
        resume: bool,
    },
    /// Run a sequence deterministic and threaded; print per-stage ms/frame, throughput
    /// against real time and ATE; write OUT/bench_tracking.md and both runs' outputs.
    Tracking {
        /// TUM RGB-D folder.
        #[arg(long)]
        sequence: PathBuf,
        /// Config file (TOML).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Output folder.
        #[arg(long, default_value = "out/bench")]
        out: PathBuf,
        /// Reuse a mode's run that a stopped (Ctrl-C) or earlier benchmark with the same
        /// sequence and config finished in OUT; only the other runs.
        #[arg(long)]
        resume: bool,
        /// Suppress depth (monocular), as `homing run --mono`; ATE is Sim3-aligned.
        #[arg(long)]
        mono: bool,
    },
    /// The paper's case study (Table II): generate both sessions, run every controller,
    /// write OUT/case_study.md (side by side) and OUT/case_study.json.
    ///
    /// Example: homing bench case-study --out out/case-study
    CaseStudy {
        /// Output folder.
        #[arg(long, default_value = "out/case-study")]
        out: PathBuf,
        /// A case study generated before (with session1/ and session2/); default: generate
        /// it into OUT/data with the homing-datasets binary.
        #[arg(long)]
        data: Option<PathBuf>,
        /// Generate the small version (320x240, 5 Hz: a pipeline check, not a tracking test).
        #[arg(long)]
        small: bool,
        /// Threaded mode (local BA on its own thread).
        #[arg(long)]
        threaded: bool,
        /// Only these controllers (repeatable); default: ours, orbslam2, proslam, ldso.
        #[arg(long, value_enum)]
        controller: Vec<ControllerKind>,
        /// Config file (TOML) for every run; the camera still comes from the sequences.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Reuse the controllers that a stopped (Ctrl-C) or earlier case study with the same
        /// data, config and mode finished in OUT; only the others run.
        #[arg(long)]
        resume: bool,
    },
    /// The robustness benchmark (issue #9): every sequence under a grid of perturbations (none,
    /// kidnapping at 1-3 places of 1-5 s, false frames at 1 % and 5 %, a dark stretch, depth
    /// suppressed) and every controller, each run a child `homing run` whose command is
    /// recorded. Writes OUT/robustness.csv, OUT/robustness.md (tables and verdicts on the
    /// issue's targets), OUT/robustness.png (coverage after kidnapping, per controller) and
    /// OUT/runs/SEQUENCE/PERTURBATION/CONTROLLER/.
    ///
    /// Example: homing bench robustness --sequence data/fr1_xyz --out out/robustness
    Robustness {
        /// TUM RGB-D folders (repeatable).
        #[arg(long, required_unless_present_any = ["plot_only", "collect"], num_args = 1..)]
        sequence: Vec<PathBuf>,
        /// Only redraw OUT/robustness.png from OUT/robustness.csv (no runs).
        #[arg(long)]
        plot_only: bool,
        /// Run nothing: write the plan (OUT/jobs.txt, one `homing` command a line, and
        /// OUT/jobs.json) and the inputs its jobs share, for a cluster's job array
        /// (scripts/slurm/robustness.sbatch) or any other executor; then `--collect OUT`.
        #[arg(long, conflicts_with_all = ["plot_only", "resume"])]
        plan_only: bool,
        /// Build OUT/robustness.{csv,md,json,png} (and the case study's table) from the run
        /// folders of the plan in DIR, whoever ran its lines; the lines not finished are
        /// listed (DIR/unfinished.txt) and the command fails until they are.
        #[arg(long, value_name = "DIR", conflicts_with_all = ["sequence", "plot_only", "plan_only", "resume"])]
        collect: Option<PathBuf>,
        /// Run every row monocular (depth suppressed); no separate depth-suppressed row.
        #[arg(long)]
        mono: bool,
        /// Only these controllers (repeatable); default: ours, orbslam2, proslam, ldso.
        #[arg(long, value_enum)]
        controller: Vec<ControllerKind>,
        /// Runs at once (default: the core count).
        #[arg(long)]
        jobs: Option<usize>,
        /// Reduced grid: no perturbation and one kidnapping (a pipeline check).
        #[arg(long)]
        quick: bool,
        /// Move every kidnapping's drops by this many seconds (under 0.5 either way; negative:
        /// earlier), to see whether a verdict depends on where exactly the drops fall.
        #[arg(
            long,
            default_value_t = 0.0,
            allow_hyphen_values = true,
            value_name = "SECONDS"
        )]
        drop_shift: f64,
        /// Output folder.
        #[arg(long, default_value = "out/robustness")]
        out: PathBuf,
        /// Config file (TOML) for every run.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Also run this case study (as `homing bench case-study --data DIR`, generated into
        /// DIR first if it is not there) and append its Table II to the report.
        #[arg(long, value_name = "DIR")]
        case_study: Option<PathBuf>,
        /// Reuse the runs that a stopped (Ctrl-C) or earlier benchmark with the same commands
        /// finished in OUT; only the others run.
        #[arg(long)]
        resume: bool,
    },
    /// How much place evidence two stretches of a sequence share, by the ground truth: per
    /// query frame, the reference frame whose key points (with depth) it sees most and finds
    /// by descriptor, with a chance-level control. Tells a missed closure from an absent one.
    ///
    /// Example: homing bench overlap --sequence data/small/aliasing --reference 7:18.8 --query 22:32
    Overlap {
        /// TUM RGB-D folder with groundtruth.txt.
        #[arg(long)]
        sequence: PathBuf,
        /// The reference stretch, START:END in seconds from the first frame.
        #[arg(long, value_name = "START:END", value_parser = parse_seconds_span)]
        reference: (f64, f64),
        /// The query stretch, START:END in seconds from the first frame.
        #[arg(long, value_name = "START:END", value_parser = parse_seconds_span)]
        query: (f64, f64),
        /// Take every n-th frame of each stretch.
        #[arg(long, default_value_t = 5)]
        every: usize,
        /// Search radius around the ground-truth projection (pixels at level 0).
        #[arg(long, default_value_t = 8.0)]
        radius: f64,
        /// Config file (TOML): the run's camera and ORB settings.
        #[arg(long)]
        config: Option<PathBuf>,
    },
}

/// `START:END` in seconds (`7:18.8`, `7s:18.8s`), START < END.
fn parse_seconds_span(s: &str) -> std::result::Result<(f64, f64), String> {
    let (a, b) = s
        .split_once(':')
        .ok_or_else(|| format!("'{s}' is not START:END"))?;
    let num = |x: &str| {
        x.trim()
            .trim_end_matches('s')
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite() && *v >= 0.0)
            .ok_or_else(|| format!("'{x}' is not a number of seconds"))
    };
    let (a, b) = (num(a)?, num(b)?);
    if a >= b {
        return Err(format!("'{s}': START must be before END"));
    }
    Ok((a, b))
}

#[derive(Args)]
struct RunArgs {
    /// TUM RGB-D folder (rgb.txt, depth.txt, rgb/, depth/, optional groundtruth.txt).
    #[arg(long, required_unless_present = "mcap")]
    sequence: Option<PathBuf>,
    /// Read a ROS 2 bag in MCAP instead of --sequence (sensor_msgs/msg/Image in cdr).
    #[arg(long, value_name = "BAG.mcap", conflicts_with = "sequence", requires_all = ["image_topic", "depth_topic"])]
    mcap: Option<PathBuf>,
    /// With --mcap: the colour image topic (rgb8, bgr8 or mono8).
    #[arg(long, value_name = "TOPIC")]
    image_topic: Option<String>,
    /// With --mcap: the depth image topic (16UC1 millimetres or 32FC1 metres).
    #[arg(long, value_name = "TOPIC")]
    depth_topic: Option<String>,
    /// With --mcap: a sensor_msgs/msg/CameraInfo topic for intrinsics and distortion.
    #[arg(long, value_name = "TOPIC")]
    camera_info_topic: Option<String>,
    /// Log the run to a rerun recording (image and keypoints, pose, trajectory, maps,
    /// closures, state). Needs a build with `--features rerun`.
    #[arg(long, value_name = "FILE.rrd", conflicts_with = "rerun_connect")]
    rerun: Option<PathBuf>,
    /// Stream the run to a live rerun viewer, e.g. 127.0.0.1:9876 (start `rerun` first).
    /// Needs a build with `--features rerun`.
    #[arg(long, value_name = "ADDR")]
    rerun_connect: Option<String>,
    /// Also write OUTDIR/run.mcap: poses, states, per-frame statistics, transitions (Foxglove).
    #[arg(long)]
    mcap_log: bool,
    /// With --mcap-log: per-stage milliseconds per frame too (measured, so run.mcap then
    /// differs run to run).
    #[arg(long, requires = "mcap_log")]
    mcap_timing: bool,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// Config file (TOML). Without it, defaults and the camera picked from the sequence.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Remove frames START:END (frame indices, or seconds from the start with '.' or 's':
    /// 120:240, 4.0:8.0, 4s:8s) so the camera jumps (kidnapping). Repeatable.
    #[arg(long = "drop", value_name = "START:END")]
    drops: Vec<DropSpec>,
    /// Replace frames by false measurements: KIND@FRAMES with KIND black|noise|frozen|foreign,
    /// FRAMES like 100,200-205. Repeatable.
    #[arg(long = "fault", value_name = "KIND@FRAMES")]
    faults: Vec<FaultSpec>,
    /// Each frame becomes a KIND fault with probability P (KIND:P). Repeatable.
    #[arg(long = "fault-rate", value_name = "KIND:P")]
    fault_rates: Vec<FaultRate>,
    /// Depth out of register with colour: PX pixels in a direction drawn from the seed, or
    /// DX,DY pixels (right, down). Every depth image is moved against its colour image.
    #[arg(
        long = "depth-shift",
        value_name = "PX|DX,DY",
        allow_hyphen_values = true
    )]
    depth_shift: Option<DepthShift>,
    /// Seed for random faults (and a --depth-shift's direction).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Suppress depth (monocular).
    #[arg(long)]
    mono: bool,
    /// Evaluate against the sequence's groundtruth.txt and print the result.
    #[arg(long)]
    eval: bool,
    /// Threaded mode: local BA on its own thread (faster; results vary slightly run to run).
    /// Default: deterministic, byte-identical outputs for the same input.
    #[arg(long)]
    threaded: bool,
    /// The modal controller: ours (the paper's state machine) or a peer's (orbslam2, proslam,
    /// ldso) on the same components. Default: the config's `controller.kind`.
    #[arg(long, value_enum)]
    controller: Option<ControllerKind>,
    /// Disable loop closing (detection, validation, global optimisation).
    #[arg(long)]
    no_loop_closing: bool,
    /// Stop at the first frame that cannot be read (missing, truncated or corrupt image,
    /// wrong size or depth format), writing the outputs so far. Without it such a frame is a
    /// failed measurement, like a black frame: a warning names the file and summary.json lists
    /// it.
    #[arg(long)]
    strict_input: bool,
    /// Init loads this saved atlas from an earlier session (multi-session).
    #[arg(long, value_name = "FILE")]
    load_map: Option<PathBuf>,
    /// Final saves the atlas to this file.
    #[arg(long, value_name = "FILE")]
    save_map: Option<PathBuf>,
    /// Read the frames from this file of decoded frames instead of decoding the images
    /// (`homing bench robustness` writes one per sequence and gives it to its runs; the
    /// outputs are the same). Checked against the sequence's frame list and camera.
    #[arg(long, value_name = "FILE")]
    decoded_frames: Option<PathBuf>,
    /// Take unperturbed frames' ORB features from this file instead of extracting them again
    /// (`homing bench robustness` writes one per sequence; the outputs are the same, and the
    /// extraction time recorded in the file is counted as the run's). Checked against the
    /// sequence's frame list, camera and ORB settings.
    #[arg(long, value_name = "FILE")]
    features: Option<PathBuf>,
}

#[derive(Args)]
struct EvalArgs {
    /// Ground truth, TUM format (default with --run: the run's sequence's groundtruth.txt).
    #[arg(long)]
    gt: Option<PathBuf>,
    /// Estimate, TUM format (default with --run: OUTDIR/trajectory.txt).
    #[arg(long)]
    est: Option<PathBuf>,
    /// A `homing run` output folder: also judge its closures (wrong: > 0.3 m or > 10° from
    /// the ground truth's relative pose) and report the ATE of each map and of the largest.
    #[arg(long, value_name = "OUTDIR")]
    run: Option<PathBuf>,
    /// Alignment before ATE: se3 (RGB-D), sim3 (monocular) or none.
    #[arg(long, value_enum, default_value = "se3")]
    align: Alignment,
    /// RPE delta.
    #[arg(long, default_value_t = 1.0)]
    rpe_delta: f64,
    /// Unit of the RPE delta.
    #[arg(long, value_enum, default_value = "s")]
    rpe_unit: RpeUnit,
    /// RPE over all (overlapping) pairs; in frames the default is evo's non-overlapping pairs.
    #[arg(long)]
    all_pairs: bool,
    /// Maximum time difference for associating estimate and ground truth (seconds).
    #[arg(long, default_value_t = 0.02)]
    max_dt: f64,
    /// The sequence the estimate came from: coverage is the share of its frames that have
    /// ground truth and a pose. Without it, coverage is taken from a summary.json next to EST.
    #[arg(long)]
    sequence: Option<PathBuf>,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
    /// Write a plot (top view and error over time) to this PNG file.
    #[arg(long)]
    plot: Option<PathBuf>,
}

fn main() {
    let cli = Cli::parse();
    let level = match (cli.quiet, cli.verbose) {
        (true, _) => "warn",
        (false, 0) => "info",
        (false, 1) => "debug",
        _ => "trace",
    };
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(level)),
        )
        .with_writer(|| cli_progress::LogWriter)
        .with_target(false)
        .init();
    let result = match cli.cmd {
        Cmd::Run(a) => cmd_run(*a, cli.quiet),
        Cmd::Report { dir, gt, out } => {
            homing::outputs::report::write_report(&dir, gt.as_deref(), out.as_deref())
                .map(|p| println!("wrote {}", p.display()))
                .map_err(Into::into)
        }
        Cmd::Eval(a) => cmd_eval(a),
        Cmd::Config { check } => cmd_config(check),
        Cmd::Convert(ConvertCmd::TumToMcap { dir, out, depth_mm }) => {
            cmd_tum_to_mcap(&dir, &out, depth_mm)
        }
        Cmd::States {
            dot: _,
            controller,
            out,
            png,
        } => cmd_states(controller, out, png),
        Cmd::Bench(BenchCmd::Memory {
            sequence,
            repeats,
            config,
            out,
            resume,
        }) => {
            // Ctrl-C: the run under way stops, no new one starts, the finished rows are written.
            if let Err(e) = homing::interrupt::install() {
                tracing::warn!("{e}: Ctrl-C will kill the benchmark");
            }
            homing::bench::memory::memory(&homing::bench::memory::Options {
                sequence,
                repeats,
                out,
                config,
                exe: None,
                resume,
            })
            .map(|md| print!("\n{md}"))
            .map_err(Into::into)
        }
        Cmd::Bench(BenchCmd::Tracking {
            sequence,
            config,
            out,
            resume,
            mono,
        }) => {
            // Ctrl-C: the run under way stops (writing its outputs), the other does not start.
            if let Err(e) = homing::interrupt::install() {
                tracing::warn!("{e}: Ctrl-C will kill the benchmark");
            }
            homing::bench::tracking(&sequence, config.as_deref(), mono, &out, resume)
                .map(|md| print!("{md}"))
                .map_err(Into::into)
        }
        Cmd::Bench(BenchCmd::Overlap {
            sequence,
            reference,
            query,
            every,
            radius,
            config,
        }) => {
            let opts = homing::bench::overlap::OverlapOptions {
                reference,
                query,
                every,
                radius_px: radius,
            };
            homing::bench::overlap::overlap(&sequence, config.as_deref(), &opts)
                .map(|r| {
                    print!(
                        "{}",
                        r.markdown(&std::env::args().collect::<Vec<_>>().join(" "))
                    )
                })
                .map_err(Into::into)
        }
        Cmd::Bench(BenchCmd::CaseStudy {
            out,
            data,
            small,
            threaded,
            controller,
            config,
            resume,
        }) => cmd_case_study(out, data, small, threaded, controller, config, resume),
        Cmd::Bench(BenchCmd::Robustness {
            collect: Some(dir), ..
        }) => cmd_collect(&dir),
        Cmd::Bench(BenchCmd::Robustness {
            plot_only: true,
            out,
            ..
        }) => {
            use homing::bench::robustness_plot::{plot_coverage, read_csv};
            let png = out.join("robustness.png");
            read_csv(&out.join("robustness.csv"))
                .and_then(|rows| plot_coverage(&png, &rows))
                .map(|drawn| {
                    if drawn {
                        println!("written: {}", png.display());
                    } else {
                        println!("no kidnapping rows: nothing to plot");
                    }
                })
                .map_err(Into::into)
        }
        Cmd::Bench(BenchCmd::Robustness {
            sequence,
            plot_only: false,
            plan_only,
            collect: None,
            mono,
            controller,
            jobs,
            quick,
            drop_shift,
            out,
            config,
            case_study,
            resume,
        }) => {
            // Ctrl-C: the runs under way stop (each writes its outputs), no new one starts,
            // and the finished rows are written; `--resume` goes on from there.
            if let Err(e) = homing::interrupt::install() {
                tracing::warn!("{e}: Ctrl-C will kill the benchmark");
            }
            let opts = homing::bench::robustness::Options {
                sequences: sequence,
                mono,
                controllers: controller,
                jobs: jobs.unwrap_or(0),
                quick,
                drop_shift,
                out: out.clone(),
                config,
                case_study,
                exe: None,
                resume,
            };
            if plan_only {
                cmd_plan(&opts)
            } else {
                homing::bench::robustness::robustness(&opts)
                .map(|(_, md)| {
                    print!("\n{md}");
                    println!(
                        "\nwritten: {0}/robustness.csv, {0}/robustness.md, {0}/robustness.json, {0}/robustness.png",
                        out.display()
                    );
                })
                .map_err(Into::into)
            }
        }
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
    if homing::interrupt::stop_requested() {
        eprintln!("stopped by the user: the finished results are written");
        std::process::exit(homing::interrupt::EXIT_STATUS);
    }
}

/// `bench robustness --plan-only`: the plan written, and how to run it.
fn cmd_plan(opts: &homing::bench::robustness::Options) -> Result<()> {
    use homing::bench::plan::{JOBS_JSON, JOBS_TXT};
    let plan = homing::bench::robustness::plan_only(opts)?;
    let out = std::path::absolute(&opts.out).unwrap_or_else(|_| opts.out.clone());
    let n = plan.jobs.len();
    println!(
        "written: {0}/{JOBS_TXT} ({n} jobs, one a line), {0}/{JOBS_JSON}",
        out.display()
    );
    println!(
        "run it: sbatch --array=1-{n}%M --export=ALL,PLAN={0} scripts/slurm/robustness.sbatch \
         (or any executor of {0}/{JOBS_TXT}), then: homing bench robustness --collect {0}",
        out.display()
    );
    Ok(())
}

/// `bench robustness --collect DIR`: the reports from the plan's run folders; fails (after
/// writing them) while lines are not finished, naming them.
fn cmd_collect(dir: &std::path::Path) -> Result<()> {
    let c = homing::bench::robustness::collect(dir)?;
    print!("\n{}", c.md);
    println!(
        "\nwritten: {0}/robustness.csv, {0}/robustness.md, {0}/robustness.json, {0}/robustness.png",
        dir.display()
    );
    if c.unfinished.is_empty() {
        return Ok(());
    }
    for (line, why) in &c.unfinished {
        eprintln!("line {line}: {why}");
    }
    let lines: Vec<usize> = c.unfinished.iter().map(|u| u.0).collect();
    Err(anyhow::anyhow!(
        "{} of the plan's jobs are not finished (listed in {}): run lines {} again (sbatch --array={} ...), then collect again",
        lines.len(),
        dir.join(homing::bench::plan::UNFINISHED_TXT).display(),
        homing::bench::plan::array_spec(&lines),
        homing::bench::plan::array_spec(&lines)
    ))
}

fn cmd_run(a: RunArgs, quiet: bool) -> Result<()> {
    // Ctrl-C / SIGTERM: the Interruptible state's user stop, not the end of the process.
    homing::interrupt::install()?;
    let mcap = a.mcap.map(|bag| {
        let topics = homing::io::mcap::McapTopics {
            image: a.image_topic.unwrap_or_default(),
            depth: a.depth_topic.unwrap_or_default(),
            camera_info: a.camera_info_topic,
        };
        (bag, topics)
    });
    let opts = RunOptions {
        sequence: a.sequence.unwrap_or_default(),
        mcap,
        mcap_log: a.mcap_log,
        mcap_timing: a.mcap_timing,
        out: a.out.clone(),
        config: a.config,
        perturb: PerturbationSpec {
            drops: a.drops,
            faults: a.faults,
            fault_rates: a.fault_rates,
            seed: a.seed,
            mono: a.mono,
            depth_shift: a.depth_shift,
        },
        eval: a.eval,
        command: std::env::args().collect(),
        threaded: a.threaded,
        controller: a.controller,
        no_loop_closing: a.no_loop_closing,
        load_map: a.load_map,
        save_map: a.save_map,
        decoded_frames: a.decoded_frames,
        features: a.features,
        rerun: match (a.rerun, a.rerun_connect) {
            (Some(f), _) => Some(homing::outputs::viz::RerunTarget::File(f)),
            (None, Some(addr)) => Some(homing::outputs::viz::RerunTarget::Connect(addr)),
            (None, None) => None,
        },
        progress: cli_progress::start(quiet),
        strict_input: a.strict_input,
    };
    let s = run(&opts);
    cli_progress::finish();
    let s = s?;
    println!(
        "{} frames delivered ({} in the sequence), {} with a pose, {} keyframes, {} maps, final state {}",
        s.frames, s.sequence_frames, s.frames_with_pose, s.keyframes, s.maps, s.final_state
    );
    if s.evaluation.is_some() {
        // The full evaluation is in summary.json.
        print!("results\n{}", homing::outputs::report::results_table(&s));
    }
    println!("outputs in {}", a.out.display());
    if let Some(u) = &s.user_stop {
        eprintln!(
            "stopped by the user after frame {} ({} frames not processed; refinement {})",
            u.frame, u.frames_not_processed, u.refinement
        );
        std::process::exit(homing::interrupt::EXIT_STATUS);
    }
    Ok(())
}

fn cmd_eval(a: EvalArgs) -> Result<()> {
    let r = eval::report::evaluate(&eval::report::EvalRequest {
        gt: a.gt,
        est: a.est,
        run: a.run.clone(),
        align: a.align,
        rpe_delta: a.rpe_delta,
        rpe_unit: a.rpe_unit,
        all_pairs: a.all_pairs,
        max_dt: a.max_dt,
        sequence: a.sequence,
    })?;
    if let Some(p) = &a.plot {
        let title = format!("{} vs {}", r.est_path.display(), r.gt_path.display());
        eval::plot::plot_ate(p, &r.gt_poses, &r.associated, &r.ate, &title)?;
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
        return Ok(());
    }
    let s = &r.ate.stats;
    println!(
        "ATE ({:?}-aligned, {} associated poses of {} estimated)",
        a.align, r.ate.pairs, r.estimate_poses
    );
    println!("  rmse   {:.6} m", s.rmse);
    println!("  mean   {:.6} m", s.mean);
    println!("  median {:.6} m", s.median);
    println!("  std    {:.6} m", s.std);
    println!("  min    {:.6} m", s.min);
    println!("  max    {:.6} m", s.max);
    if a.align == Alignment::Sim3 {
        println!("  scale  {:.6}", r.ate.scale);
    }
    match (&r.rpe, &r.rpe_error) {
        (Some(p), _) => {
            println!("RPE (delta {} {:?}, {} pairs)", p.delta, p.unit, p.pairs);
            println!("  trans rmse {:.6} m", p.trans.rmse);
            println!("  rot   rmse {:.6} deg", p.rot_deg.rmse);
        }
        (None, e) => println!("RPE: {}", e.as_deref().unwrap_or("none")),
    }
    match r.coverage {
        Some(c) => println!("coverage {:.2} %", 100.0 * c),
        None => println!("coverage: unknown (pass --sequence DIR)"),
    }
    if let (Some(c), Some(per_map)) = (&r.closures, &r.maps) {
        println!(
            "closures: {} candidates ({} wrong); accepted {} ({} wrong{}), rolled back {} ({} wrong), rejected {} ({} wrong), expired {} ({} wrong)",
            c.candidates,
            c.candidates_wrong,
            c.accepted,
            c.accepted_wrong,
            if c.accepted_wrong_frames.is_empty() {
                String::new()
            } else {
                format!(": frames {:?}", c.accepted_wrong_frames)
            },
            c.rolled_back,
            c.rolled_back_wrong,
            c.rejected,
            c.rejected_wrong,
            c.expired,
            c.expired_wrong
        );
        for m in per_map {
            println!(
                "map {}{}: {} poses, ATE rmse {}",
                m.map,
                if Some(m.map) == r.largest_map {
                    " (largest)"
                } else {
                    ""
                },
                m.poses,
                m.ate_rmse_m
                    .map_or("n/a (too few poses)".into(), |r| format!("{r:.6} m"))
            );
        }
    }
    Ok(())
}

fn cmd_tum_to_mcap(dir: &std::path::Path, out: &std::path::Path, depth_mm: bool) -> Result<()> {
    let t0 = std::time::Instant::now();
    let s = homing::io::mcap::tum_to_mcap(dir, out, depth_mm)?;
    println!(
        "wrote {}: {} colour, {} depth, {} CameraInfo ({}), {} ground-truth messages, {:.1} MB in {:.1} s",
        out.display(),
        s.colour,
        s.depth,
        s.camera_info,
        s.camera.as_deref().unwrap_or("camera unknown"),
        s.groundtruth,
        s.bytes as f64 / 1e6,
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

fn cmd_config(check: Option<PathBuf>) -> Result<()> {
    let cfg = match &check {
        Some(p) => Config::load(p)?,
        None => Config::default(),
    };
    print!("{}", toml::to_string(&cfg)?);
    if let Some(p) = check {
        eprintln!("{}: valid", p.display());
    }
    Ok(())
}

fn cmd_states(kind: ControllerKind, out: Option<PathBuf>, png: Option<PathBuf>) -> Result<()> {
    let dot = homing::control::MachineSpec::for_kind(kind).to_dot();
    match &out {
        Some(p) => homing::io::atomic_write(p, dot.as_bytes())?,
        None => print!("{dot}"),
    }
    if let Some(png) = png {
        use std::io::Write as _;
        let mut child = std::process::Command::new("dot")
            .args(["-Tpng", "-o"])
            .arg(&png)
            .stdin(std::process::Stdio::piped())
            .spawn()
            .context("cannot run Graphviz 'dot' (install graphviz for --png)")?;
        child
            .stdin
            .take()
            .context("dot: no stdin")?
            .write_all(dot.as_bytes())?;
        let status = child.wait()?;
        if !status.success() {
            bail!("dot failed ({status}) writing {}", png.display());
        }
        eprintln!("wrote {}", png.display());
    }
    Ok(())
}

fn cmd_case_study(
    out: PathBuf,
    data: Option<PathBuf>,
    small: bool,
    threaded: bool,
    controllers: Vec<ControllerKind>,
    config: Option<PathBuf>,
    resume: bool,
) -> Result<()> {
    use homing::bench::case_study;
    // Ctrl-C: the runs under way stop (each writes its outputs), no new one starts, and the
    // finished controllers are written; `--resume` goes on from there.
    if let Err(e) = homing::interrupt::install() {
        tracing::warn!("{e}: Ctrl-C will kill the benchmark");
    }
    let data = match data {
        Some(d) => d,
        None => {
            let d = out.join("data");
            if !d.join("session2/scenario.json").is_file() {
                case_study::generate(&d, small)?;
            }
            d
        }
    };
    let controllers = if controllers.is_empty() {
        case_study::CONTROLLERS.to_vec()
    } else {
        controllers
    };
    let opts = case_study::Options {
        threaded,
        controllers,
        config,
        jobs: 0,
        resume,
        collect_only: false,
    };
    let (_, md) = case_study::case_study(&data, &out, &opts)?;
    print!("{md}");
    println!(
        "\nwritten: {0}/case_study.md, {0}/case_study.json",
        out.display()
    );
    Ok(())
}
