//! Sensor model: turns a raw render into what a Kinect-like RGB-D camera would deliver.
//! Every effect can be switched off separately; the random draws come from a ChaCha RNG seeded
//! from (seed, frame, row), so output is identical for any number of threads.

use homing::io::tum::DepthImage;
use image::RgbImage;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;
use serde::Serialize;

use crate::render::RenderOut;
use crate::texture::mix;

/// Which realism effects are on. Serialised into scenario.json.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SensorOptions {
    /// Axial depth noise sigma = 1.425e-3 z^2 m (Nguyen et al. 2012 / Kinect v1).
    pub depth_noise: bool,
    /// Small random holes (invalid depth blobs), as speckle/IR dropouts in real depth maps.
    pub depth_holes: bool,
    /// Depth beyond this range (m) is invalid (0); also below `min_range`.
    pub max_range: f64,
    pub min_range: f64,
    /// Depth at incidence angles above this (degrees from the normal) is invalid.
    pub grazing_deg: f64,
    /// Additive Gaussian noise on the 8-bit colour image (sigma in grey levels).
    pub image_noise: bool,
    pub image_noise_sigma: f64,
    /// Average of 5 renders over a 20 ms exposure centred on the stamp.
    pub motion_blur: bool,
    /// Depth stamps differ from colour stamps by 3–12 ms, and colour stamps jitter by
    /// +-1 ms, so colour and depth must be associated like real TUM data.
    pub time_offset: bool,
    /// The scenario's dark stretches (lights off) are rendered dark. Not noise: kept on by
    /// `--clean`, off only with `--no-darkness`.
    pub darkness: bool,
}

impl SensorOptions {
    pub fn realistic() -> Self {
        Self {
            depth_noise: true,
            depth_holes: true,
            max_range: 4.5,
            min_range: 0.4,
            grazing_deg: 80.0,
            image_noise: true,
            image_noise_sigma: 2.0,
            motion_blur: false,
            time_offset: true,
            darkness: true,
        }
    }

    /// Exact depth (still quantised by the 16-bit PNG), no image noise, no holes, equal stamps.
    /// Range limits and grazing-angle dropouts stay (they are geometry, not noise) but are
    /// widened so that every surface pixel keeps its depth.
    pub fn clean() -> Self {
        Self {
            depth_noise: false,
            depth_holes: false,
            max_range: 13.0,
            min_range: 0.0,
            grazing_deg: 90.0,
            image_noise: false,
            image_noise_sigma: 0.0,
            motion_blur: false,
            time_offset: false,
            darkness: true,
        }
    }
}

fn rng_for(seed: u64, frame: u64, stream: u64, row: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(mix(seed ^ mix(frame ^ mix(stream ^ mix(row)))))
}

/// 8-bit colour image from the render, with exposure `gain` and optional noise.
pub fn colour_image(
    r: &RenderOut,
    gain: f32,
    opts: &SensorOptions,
    seed: u64,
    frame: u64,
) -> RgbImage {
    let (w, h) = (r.width as usize, r.height as usize);
    let mut buf = vec![0u8; w * h * 3];
    let sigma = if opts.image_noise {
        opts.image_noise_sigma
    } else {
        0.0
    };
    buf.par_chunks_mut(w * 3).enumerate().for_each(|(y, row)| {
        let mut rng = rng_for(seed, frame, 1, y as u64);
        let normal = Normal::new(0.0f32, sigma.max(1e-9) as f32).expect("finite sigma");
        for (i, px) in row.iter_mut().enumerate() {
            let lin = (r.rgb[y * w * 3 + i] * gain).clamp(0.0, 1.0);
            // Texture colours are display values already: no tone curve.
            let mut v = lin * 255.0;
            if sigma > 0.0 {
                v += normal.sample(&mut rng);
            }
            *px = v.round().clamp(0.0, 255.0) as u8;
        }
    });
    RgbImage::from_raw(r.width, r.height, buf).expect("buffer size matches")
}

/// Depth image in metres from the render, with the enabled depth effects.
pub fn depth_image(r: &RenderOut, opts: &SensorOptions, seed: u64, frame: u64) -> DepthImage {
    let (w, h) = (r.width as usize, r.height as usize);
    let mut data = vec![0f32; w * h];
    let min_cos = (opts.grazing_deg.to_radians()).cos() as f32;
    data.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let mut rng = rng_for(seed, frame, 2, y as u64);
        let n01 = Normal::new(0.0f64, 1.0).expect("unit normal");
        for (x, out) in row.iter_mut().enumerate() {
            let i = y * w + x;
            let z = r.depth[i] as f64;
            if z <= 0.0 || z > opts.max_range || z < opts.min_range || r.cos[i] < min_cos {
                *out = 0.0;
                continue;
            }
            let mut zn = z;
            if opts.depth_noise {
                zn += 1.425e-3 * z * z * n01.sample(&mut rng);
            }
            *out = zn as f32;
        }
    });
    if opts.depth_holes {
        // A few small elliptic dropouts per frame, more of them far away.
        let mut rng = rng_for(seed, frame, 3, 0);
        let n = 6 + (w * h / 40_000);
        for _ in 0..n {
            let cx = rng.random_range(0..w) as i64;
            let cy = rng.random_range(0..h) as i64;
            let z = data[cy as usize * w + cx as usize];
            if z <= 0.0 && rng.random::<f32>() < 0.7 {
                continue;
            }
            let rx = rng.random_range(1.0..(2.0 + 3.0 * w as f64 / 640.0));
            let ry = rng.random_range(1.0..(2.0 + 3.0 * w as f64 / 640.0));
            let (ix, iy) = (rx.ceil() as i64, ry.ceil() as i64);
            for yy in (cy - iy).max(0)..(cy + iy + 1).min(h as i64) {
                for xx in (cx - ix).max(0)..(cx + ix + 1).min(w as i64) {
                    let (dx, dy) = ((xx - cx) as f64 / rx, (yy - cy) as f64 / ry);
                    if dx * dx + dy * dy <= 1.0 {
                        data[yy as usize * w + xx as usize] = 0.0;
                    }
                }
            }
        }
    }
    DepthImage {
        width: r.width,
        height: r.height,
        data,
    }
}

/// Depth stamp offset and colour stamp jitter (seconds) of a frame.
pub fn stamp_offsets(opts: &SensorOptions, seed: u64, frame: u64) -> (f64, f64) {
    if !opts.time_offset {
        return (0.0, 0.0);
    }
    let mut rng = rng_for(seed, frame, 4, 0);
    let jitter = rng.random_range(-0.001..0.001);
    let depth = -rng.random_range(0.003..0.012);
    (jitter, depth)
}
