//! Perturbations applied in the sequence reader (paper section IV: "we simulate kidnapping by
//! suppressing large portions of the data in the middle of the mission and sensor failures by
//! injecting isolated false measurements at random intervals").
//!
//! A [`PerturbationSpec`] is what the user asked for; [`PerturbationPlan`] is what it means for
//! one sequence (which frames are dropped, which are replaced and by what). The plan is
//! deterministic given the spec (seeded RNG) and is written into the run's `summary.json`,
//! so that every perturbed run can be reproduced and evaluated.

use crate::error::{Error, Result};
use crate::io::tum::{DepthImage, Frame, FrameSource};
use image::RgbImage;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::fmt;

/// One end of a `--drop START:END` range.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mark {
    /// Seconds from the first frame's time stamp.
    Seconds(f64),
    /// Frame index in the unperturbed sequence.
    Frame(usize),
}

impl Mark {
    fn parse(s: &str) -> std::result::Result<Self, String> {
        let s = s.trim();
        // An 's' suffix or a decimal point means seconds; a bare integer is a frame index.
        let seconds = s.strip_suffix('s').or(s.contains('.').then_some(s));
        if let Some(sec) = seconds {
            return sec
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite() && *v >= 0.0)
                .map(Mark::Seconds)
                .ok_or_else(|| format!("'{s}' is not a non-negative number of seconds"));
        }
        s.parse::<usize>().map(Mark::Frame).map_err(|_| {
            format!("'{s}' is neither a frame index nor seconds (e.g. 120, 4.0 or 4s)")
        })
    }
}

/// `--drop START:END`: frames in [START, END) are removed, so the camera jumps (kidnapping).
/// Bare integers are frame indices, numbers with a '.' or an 's' suffix are seconds from the
/// start: `--drop 120:240`, `--drop 4.0:8.0`, `--drop 4s:8s`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DropSpec {
    pub start: Mark,
    pub end: Mark,
}

impl std::str::FromStr for DropSpec {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let (a, b) = s
            .split_once(':')
            .ok_or_else(|| format!("--drop '{s}': expected START:END"))?;
        let (start, end) = (Mark::parse(a)?, Mark::parse(b)?);
        Ok(Self { start, end })
    }
}

/// The kinds of false measurement a faulty sensor delivers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, PartialOrd, Ord)]
#[serde(rename_all = "lowercase")]
pub enum FaultKind {
    /// Black image, no depth readings.
    Black,
    /// Uniform noise in colour and depth.
    Noise,
    /// The previous delivered frame again (a stuck driver), with the new time stamp.
    Frozen,
    /// A frame from elsewhere in the sequence (at least 2 s away).
    Foreign,
}

impl FaultKind {
    fn parse(s: &str) -> std::result::Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "black" => Ok(Self::Black),
            "noise" => Ok(Self::Noise),
            "frozen" => Ok(Self::Frozen),
            "foreign" => Ok(Self::Foreign),
            o => Err(format!(
                "unknown fault kind '{o}' (black, noise, frozen, foreign)"
            )),
        }
    }
}

impl fmt::Display for FaultKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Black => "black",
            Self::Noise => "noise",
            Self::Frozen => "frozen",
            Self::Foreign => "foreign",
        })
    }
}

/// `--fault KIND@FRAMES`: frames given as a comma list of indices and ranges,
/// e.g. `black@100,200-205`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FaultSpec {
    pub kind: FaultKind,
    pub frames: Vec<usize>,
}

impl std::str::FromStr for FaultSpec {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let (k, list) = s.split_once('@').ok_or_else(|| {
            format!("--fault '{s}': expected KIND@FRAMES, e.g. black@100,200-205")
        })?;
        let kind = FaultKind::parse(k)?;
        let mut frames = Vec::new();
        for part in list.split(',').filter(|p| !p.trim().is_empty()) {
            let bad = || format!("--fault '{s}': '{part}' is not a frame index or range A-B");
            if let Some((a, b)) = part.split_once('-') {
                let a: usize = a.trim().parse().map_err(|_| bad())?;
                let b: usize = b.trim().parse().map_err(|_| bad())?;
                if b < a || b - a > 1_000_000 {
                    return Err(bad());
                }
                frames.extend(a..=b);
            } else {
                frames.push(part.trim().parse().map_err(|_| bad())?);
            }
        }
        if frames.is_empty() {
            return Err(format!("--fault '{s}': no frames given"));
        }
        Ok(Self { kind, frames })
    }
}

/// `--fault-rate KIND:P`: each frame independently becomes a KIND fault with probability P.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FaultRate {
    pub kind: FaultKind,
    pub p: f64,
}

impl std::str::FromStr for FaultRate {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let (k, p) = s
            .split_once(':')
            .ok_or_else(|| format!("--fault-rate '{s}': expected KIND:P, e.g. black:0.05"))?;
        let kind = FaultKind::parse(k)?;
        let p: f64 = p
            .trim()
            .parse()
            .ok()
            .filter(|p: &f64| (0.0..=1.0).contains(p))
            .ok_or_else(|| format!("--fault-rate '{s}': P must be a probability in [0, 1]"))?;
        Ok(Self { kind, p })
    }
}

/// `--depth-shift PX` or `--depth-shift DX,DY`: the depth image is out of register with the
/// colour image by this many pixels, as on a sensor whose depth-to-colour registration is off
/// (a factory calibration for another unit, a camera knocked about, another sensor model).
/// A single number is a length, in a direction drawn from the seed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DepthShift {
    /// This many pixels, direction from the seed.
    Length(f64),
    /// Pixels to the right and down.
    Offset(f64, f64),
}

impl std::str::FromStr for DepthShift {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let bad =
            || format!("--depth-shift '{s}': expected PX or DX,DY in pixels (e.g. 3 or 2.5,-1)");
        let num = |x: &str| -> std::result::Result<f64, String> {
            let v: f64 = x.trim().trim_end_matches("px").parse().map_err(|_| bad())?;
            (v.is_finite() && v.abs() <= 100.0)
                .then_some(v)
                .ok_or_else(bad)
        };
        match s.split_once(',') {
            Some((x, y)) => Ok(Self::Offset(num(x)?, num(y)?)),
            None => {
                let v = num(s)?;
                (v >= 0.0).then_some(Self::Length(v)).ok_or_else(bad)
            }
        }
    }
}

/// What the user asked for. Serialised into `summary.json`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PerturbationSpec {
    pub drops: Vec<DropSpec>,
    pub faults: Vec<FaultSpec>,
    pub fault_rates: Vec<FaultRate>,
    pub seed: u64,
    /// Depth suppressed (monocular).
    pub mono: bool,
    /// Depth out of register with colour.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_shift: Option<DepthShift>,
}

impl PerturbationSpec {
    pub fn is_empty(&self) -> bool {
        self.drops.is_empty()
            && self.faults.is_empty()
            && self.fault_rates.is_empty()
            && !self.mono
            && self.depth_shift.is_none()
    }
}

/// A frame replaced by a false measurement.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AppliedFault {
    pub frame: usize,
    pub kind: FaultKind,
    /// For `foreign`: the frame whose images were delivered instead.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub source: Option<usize>,
}

/// What the spec means for one sequence: the frames that are delivered (indices into the
/// unperturbed sequence, increasing) and the faults among them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PerturbationPlan {
    pub spec: PerturbationSpec,
    /// Dropped index ranges [start, end), after resolving seconds to frames.
    pub dropped: Vec<(usize, usize)>,
    pub dropped_frames: usize,
    pub faults: Vec<AppliedFault>,
    /// `--depth-shift` resolved: every depth image moved this many pixels (right, down)
    /// against its colour image.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_shift_px: Option<[f64; 2]>,
    #[serde(skip)]
    pub delivered: Vec<usize>,
}

impl PerturbationPlan {
    /// Resolves `spec` against the time stamps of a sequence.
    pub fn new(spec: &PerturbationSpec, stamps: &[f64]) -> Result<Self> {
        let n = stamps.len();
        let t0 = stamps.first().copied().unwrap_or(0.0);
        let resolve = |m: Mark| -> usize {
            match m {
                Mark::Frame(i) => i.min(n),
                Mark::Seconds(s) => stamps.partition_point(|&t| t - t0 < s),
            }
        };
        let mut dropped_mask = vec![false; n];
        let mut dropped = Vec::new();
        for d in &spec.drops {
            let (a, b) = (resolve(d.start), resolve(d.end));
            if b <= a {
                return Err(Error::invalid(format!(
                    "--drop {:?}:{:?} selects no frame of this {n}-frame sequence (start must \
                     come before end, inside the sequence)",
                    d.start, d.end
                )));
            }
            dropped_mask[a..b].iter_mut().for_each(|m| *m = true);
            dropped.push((a, b));
        }
        let mut fault_at: Vec<Option<FaultKind>> = vec![None; n];
        for f in &spec.faults {
            for &i in &f.frames {
                if i >= n {
                    return Err(Error::invalid(format!(
                        "--fault {}@{i}: frame {i} is past the end of this {n}-frame sequence",
                        f.kind
                    )));
                }
                fault_at[i] = Some(f.kind);
            }
        }
        let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
        // Rates are drawn for every frame (dropped or not), so adding a drop does not reshuffle
        // where the random faults land.
        for slot in fault_at.iter_mut() {
            for r in &spec.fault_rates {
                if rng.random::<f64>() < r.p && slot.is_none() {
                    *slot = Some(r.kind);
                }
            }
        }
        let delivered: Vec<usize> = (0..n).filter(|&i| !dropped_mask[i]).collect();
        let mut faults = Vec::new();
        for &i in &delivered {
            let Some(kind) = fault_at[i] else { continue };
            let source = (kind == FaultKind::Foreign)
                .then(|| foreign_source(stamps, i, &mut rng))
                .flatten();
            if kind == FaultKind::Foreign && source.is_none() {
                return Err(Error::invalid(format!(
                    "--fault foreign at frame {i}: the sequence has no frame 2 s away from it"
                )));
            }
            faults.push(AppliedFault {
                frame: i,
                kind,
                source,
            });
        }
        // Drawn after every fault, so that asking for a shift moves no fault.
        let depth_shift_px = spec.depth_shift.map(|d| match d {
            DepthShift::Offset(x, y) => [x, y],
            DepthShift::Length(l) => {
                let a = rng.random_range(0.0..std::f64::consts::TAU);
                [l * a.cos(), l * a.sin()]
            }
        });
        Ok(Self {
            spec: spec.clone(),
            dropped_frames: n - delivered.len(),
            dropped,
            faults,
            depth_shift_px,
            delivered,
        })
    }

    pub fn fault(&self, frame: usize) -> Option<&AppliedFault> {
        self.faults
            .binary_search_by_key(&frame, |f| f.frame)
            .ok()
            .map(|k| &self.faults[k])
    }
}

/// A frame at least 2 s away from frame `i`, drawn deterministically.
fn foreign_source(stamps: &[f64], i: usize, rng: &mut ChaCha8Rng) -> Option<usize> {
    let far: Vec<usize> = (0..stamps.len())
        .filter(|&j| (stamps[j] - stamps[i]).abs() >= 2.0)
        .collect();
    (!far.is_empty()).then(|| far[rng.random_range(0..far.len())])
}

/// A sequence seen through a perturbation plan: only delivered frames, faults substituted,
/// depth removed in mono mode. Frame indices stay those of the unperturbed sequence.
pub struct PerturbedSequence<'a> {
    inner: &'a (dyn FrameSource + Sync),
    pub plan: PerturbationPlan,
}

impl<'a> PerturbedSequence<'a> {
    pub fn new(inner: &'a (dyn FrameSource + Sync), spec: &PerturbationSpec) -> Result<Self> {
        let stamps: Vec<f64> = (0..inner.len()).map(|i| inner.timestamp(i)).collect();
        let plan = PerturbationPlan::new(spec, &stamps)?;
        Ok(Self { inner, plan })
    }

    /// Number of delivered frames.
    pub fn len(&self) -> usize {
        self.plan.delivered.len()
    }

    pub fn is_empty(&self) -> bool {
        self.plan.delivered.is_empty()
    }

    /// Delivered frames in order. `frozen` repeats the previous *delivered* frame, which is why
    /// this is an iterator and not random access.
    pub fn frames(&self) -> impl Iterator<Item = Result<Frame>> + '_ {
        let mut previous: Option<Frame> = None;
        self.plan.delivered.iter().map(move |&i| {
            let mut frame = match self.plan.fault(i) {
                None => self.inner.load(i)?,
                Some(f) => self.false_measurement(i, f, previous.as_ref())?,
            };
            if self.plan.spec.mono {
                frame.depth = None;
            }
            if let (Some(d), Some([dx, dy])) = (frame.depth.as_mut(), self.plan.depth_shift_px) {
                shift_depth(d, dx, dy);
            }
            previous = Some(frame.clone());
            Ok(frame)
        })
    }

    fn false_measurement(&self, i: usize, f: &AppliedFault, prev: Option<&Frame>) -> Result<Frame> {
        let t = self.inner.timestamp(i);
        let mut frame = match (f.kind, prev, f.source) {
            (FaultKind::Foreign, _, Some(src)) => self.inner.load(src)?,
            (FaultKind::Frozen, Some(p), _) => p.clone(),
            // A frozen first frame has nothing to repeat: the sensor delivers black.
            _ => self.inner.load(i)?,
        };
        frame.index = i;
        frame.t = t;
        match f.kind {
            FaultKind::Black => {
                frame.rgb.pixels_mut().for_each(|p| p.0 = [0, 0, 0]);
                if let Some(d) = &mut frame.depth {
                    d.data.iter_mut().for_each(|v| *v = 0.0);
                }
            }
            FaultKind::Noise => {
                // Seeded per frame so the noise does not depend on what came before.
                let mut rng = ChaCha8Rng::seed_from_u64(
                    self.plan.spec.seed ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
                );
                noise_rgb(&mut frame.rgb, &mut rng);
                if let Some(d) = &mut frame.depth {
                    noise_depth(d, &mut rng);
                }
            }
            FaultKind::Frozen if prev.is_none() => {
                frame.rgb.pixels_mut().for_each(|p| p.0 = [0, 0, 0]);
                if let Some(d) = &mut frame.depth {
                    d.data.iter_mut().for_each(|v| *v = 0.0);
                }
            }
            FaultKind::Frozen | FaultKind::Foreign => {}
        }
        Ok(frame)
    }
}

/// Moves the depth image `(dx, dy)` pixels against the colour image: the reading at (u, v) is
/// the one that was at (u − dx, v − dy), nearest pixel (interpolating would invent depths
/// between a foreground edge and what lies behind it); none where that falls outside.
fn shift_depth(d: &mut DepthImage, dx: f64, dy: f64) {
    let (w, h) = (d.width as i64, d.height as i64);
    let (ox, oy) = (dx.round() as i64, dy.round() as i64);
    let src = std::mem::take(&mut d.data);
    d.data = vec![0.0; src.len()];
    for v in 0..h {
        let sv = v - oy;
        if !(0..h).contains(&sv) {
            continue;
        }
        for u in 0..w {
            let su = u - ox;
            if (0..w).contains(&su) {
                d.data[(v * w + u) as usize] = src[(sv * w + su) as usize];
            }
        }
    }
}

fn noise_rgb(img: &mut RgbImage, rng: &mut ChaCha8Rng) {
    for p in img.pixels_mut() {
        p.0 = [rng.random(), rng.random(), rng.random()];
    }
}

fn noise_depth(d: &mut DepthImage, rng: &mut ChaCha8Rng) {
    for v in d.data.iter_mut() {
        *v = rng.random_range(0.3f32..6.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stamps(n: usize) -> Vec<f64> {
        (0..n).map(|i| 100.0 + i as f64 / 30.0).collect()
    }

    #[test]
    fn parse_specs() {
        let d: DropSpec = "120:240".parse().unwrap();
        assert_eq!(d.start, Mark::Frame(120));
        let d: DropSpec = "4.0:8s".parse().unwrap();
        assert_eq!((d.start, d.end), (Mark::Seconds(4.0), Mark::Seconds(8.0)));
        assert!("4:".parse::<DropSpec>().is_err());
        assert!("x:5".parse::<DropSpec>().is_err());
        let f: FaultSpec = "black@3,10-12".parse().unwrap();
        assert_eq!(f.frames, vec![3, 10, 11, 12]);
        assert!("purple@3".parse::<FaultSpec>().is_err());
        assert!("black@".parse::<FaultSpec>().is_err());
        assert!("noise:1.5".parse::<FaultRate>().is_err());
        assert_eq!("noise:0.05".parse::<FaultRate>().unwrap().p, 0.05);
    }

    #[test]
    fn drops_by_seconds_and_frames() {
        let spec = PerturbationSpec {
            drops: vec!["1.0:2.0".parse().unwrap(), "250:260".parse().unwrap()],
            ..Default::default()
        };
        let plan = PerturbationPlan::new(&spec, &stamps(300)).unwrap();
        assert_eq!(plan.dropped, vec![(30, 60), (250, 260)]);
        assert_eq!(plan.delivered.len(), 300 - 40);
        assert!(!plan.delivered.contains(&30) && plan.delivered.contains(&60));
    }

    #[test]
    fn a_depth_shift_moves_depth_against_colour_and_is_recorded() {
        assert_eq!("3".parse::<DepthShift>(), Ok(DepthShift::Length(3.0)));
        assert_eq!(
            "2,-1".parse::<DepthShift>(),
            Ok(DepthShift::Offset(2.0, -1.0))
        );
        assert!("-3".parse::<DepthShift>().is_err());
        assert!("x".parse::<DepthShift>().is_err());
        let spec = PerturbationSpec {
            depth_shift: Some(DepthShift::Length(8.0)),
            fault_rates: vec!["black:0.05".parse().unwrap()],
            seed: 3,
            ..Default::default()
        };
        let a = PerturbationPlan::new(&spec, &stamps(300)).unwrap();
        let [dx, dy] = a.depth_shift_px.unwrap();
        assert!(((dx * dx + dy * dy).sqrt() - 8.0).abs() < 1e-9);
        assert_eq!(a, PerturbationPlan::new(&spec, &stamps(300)).unwrap());
        let without = PerturbationSpec {
            depth_shift: None,
            ..spec.clone()
        };
        let b = PerturbationPlan::new(&without, &stamps(300)).unwrap();
        assert_eq!(a.faults, b.faults, "a shift moves no fault");
        let json = serde_json::to_string(&a).unwrap();
        assert!(json.contains("depth_shift_px"), "{json}");

        let mut d = DepthImage::new(4, 3);
        d.data = (0..12).map(|i| i as f32).collect();
        shift_depth(&mut d, 1.0, 1.0);
        assert_eq!(
            d.data,
            vec![0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 2.0, 0.0, 4.0, 5.0, 6.0]
        );
    }

    #[test]
    fn empty_or_reversed_drop_is_an_error() {
        let spec = PerturbationSpec {
            drops: vec!["50:40".parse().unwrap()],
            ..Default::default()
        };
        assert!(PerturbationPlan::new(&spec, &stamps(100)).is_err());
    }

    #[test]
    fn fault_rates_are_deterministic_and_near_p() {
        let spec = PerturbationSpec {
            fault_rates: vec![
                "black:0.05".parse().unwrap(),
                "foreign:0.01".parse().unwrap(),
            ],
            seed: 7,
            ..Default::default()
        };
        let a = PerturbationPlan::new(&spec, &stamps(3000)).unwrap();
        let b = PerturbationPlan::new(&spec, &stamps(3000)).unwrap();
        assert_eq!(a, b);
        let black = a
            .faults
            .iter()
            .filter(|f| f.kind == FaultKind::Black)
            .count();
        assert!((100..=200).contains(&black), "{black}");
        for f in a.faults.iter().filter(|f| f.kind == FaultKind::Foreign) {
            let src = f.source.unwrap();
            assert!((src as f64 - f.frame as f64).abs() >= 60.0);
        }
        let other = PerturbationSpec { seed: 8, ..spec };
        assert_ne!(
            PerturbationPlan::new(&other, &stamps(3000)).unwrap().faults,
            a.faults
        );
    }
}
