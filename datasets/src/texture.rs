//! Procedural surface textures.
//!
//! Textures are evaluated analytically instead of being stored as images: each texture is a
//! stack of levels, each level a grid of cells, and a cell may hold one shape (rectangle,
//! disc or hollow frame) whose parameters come from a hash of (seed, level, cell). This gives
//! unlimited resolution with no memory, sharp corners at several scales (what FAST/ORB needs),
//! and exact reproducibility: two surfaces with the same seed and the same texture origin look
//! identical, which is how perceptual aliasing is built. Anti-aliasing is analytic: every
//! shape's coverage is box-filtered with the pixel footprint on the surface, and levels whose
//! cells are smaller than a few footprints fade out (a continuous mip-map).

/// SplitMix64 finaliser: a cheap, well-mixed, platform-independent hash.
pub fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Hash of a seed and a few integers.
pub fn hash3(seed: u64, a: u64, b: i64, c: i64) -> u64 {
    mix(seed ^ mix(a ^ mix((b as u64).wrapping_mul(0x2545_F491_4F6C_DD1D) ^ mix(c as u64))))
}

/// The k-th uniform number in [0, 1) drawn from hash `h`.
#[inline]
pub fn unit(h: u64, k: u64) -> f32 {
    (mix(h.wrapping_add(k.wrapping_mul(0x9E37_79B9_7F4A_7C15))) >> 40) as f32 / (1u64 << 24) as f32
}

/// Up to 20 uniform numbers of a cell, four 16-bit fields per hash word: one hash per four
/// numbers keeps sampling cheap (texture sampling dominates the render time).
struct CellRand([u64; 5]);

impl CellRand {
    fn new(h: u64) -> Self {
        Self([mix(h ^ 1), mix(h ^ 2), mix(h ^ 3), mix(h ^ 4), mix(h ^ 5)])
    }
    #[inline]
    fn get(&self, k: u64) -> f32 {
        let w = self.0[(k / 4) as usize];
        ((w >> (16 * (k % 4))) & 0xFFFF) as f32 / 65536.0
    }
}

/// One scale of shapes.
#[derive(Debug, Clone)]
pub struct Level {
    /// Cell size in metres.
    pub cell: f64,
    /// Probability that a cell holds a shape.
    pub density: f32,
    /// Probability of a disc (else rectangle or frame).
    pub disc: f32,
    /// Probability of a hollow frame among the non-discs.
    pub frame: f32,
    /// Rectangles are stretched along u by up to this factor (planks, books, tiles).
    pub stretch: f32,
    /// How far shape colours may be from the base lightness (0..1).
    pub contrast: f32,
}

/// A procedural texture; `sample` is pure, so rendering is deterministic and thread-safe.
#[derive(Debug, Clone)]
pub struct Texture {
    pub seed: u64,
    pub base: [f32; 3],
    pub levels: Vec<Level>,
    /// Optional border (width in metres, colour) inside a rectangle of the given size: posters
    /// and picture frames get a dark, sharp outline that tests can find.
    pub border: Option<(f64, [f32; 3], [f64; 2])>,
}

/// Box-filtered 1-D coverage of [a, b] by a pixel footprint of width `w` centred at `x`.
#[inline]
fn cov1(x: f64, a: f64, b: f64, w: f64) -> f32 {
    let lo = (x - 0.5 * w).max(a);
    let hi = (x + 0.5 * w).min(b);
    ((hi - lo) / w).clamp(0.0, 1.0) as f32
}

#[inline]
fn lerp3(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

/// A colour of random hue whose lightness is pushed away from `base_l` by up to `contrast`.
fn shape_colour(h: &CellRand, base_l: f32, contrast: f32) -> [f32; 3] {
    let dir = if h.get(11) < 0.5 { -1.0 } else { 1.0 };
    let mut l = base_l + dir * contrast * (0.35 + 0.65 * h.get(12));
    if !(0.03..=0.97).contains(&l) {
        l = base_l - dir * contrast * (0.35 + 0.65 * h.get(12));
    }
    let l = l.clamp(0.03, 0.97);
    let sat = 0.6 * h.get(13);
    let hue = [h.get(14) - 0.5, h.get(15) - 0.5, h.get(16) - 0.5];
    [
        (l * (1.0 + sat * hue[0])).clamp(0.0, 1.0),
        (l * (1.0 + sat * hue[1])).clamp(0.0, 1.0),
        (l * (1.0 + sat * hue[2])).clamp(0.0, 1.0),
    ]
}

fn lightness(c: [f32; 3]) -> f32 {
    0.299 * c[0] + 0.587 * c[1] + 0.114 * c[2]
}

impl Texture {
    /// Colour at surface coordinates (u, v) in metres, for a pixel footprint `w` metres wide.
    pub fn sample(&self, u: f64, v: f64, w: f64) -> [f32; 3] {
        let mut col = self.base;
        for (li, lv) in self.levels.iter().enumerate() {
            let c = lv.cell;
            // Fade a level out once its cells span fewer than ~3 footprints.
            let fade = ((0.35 * c - w) / (0.2 * c)).clamp(0.0, 1.0) as f32;
            if fade <= 0.0 {
                continue;
            }
            let (fi, fj) = ((u / c).floor(), (v / c).floor());
            let h0 = hash3(self.seed, li as u64, fi as i64, fj as i64);
            if ((h0 >> 40) as f32 / (1u64 << 24) as f32) >= lv.density {
                continue;
            }
            let h = CellRand::new(h0);
            let (x, y) = (u - fi * c, v - fj * c);
            let cov = if h.get(1) < lv.disc {
                let (cx, cy) = (
                    (0.35 + 0.3 * h.get(2)) as f64 * c,
                    (0.35 + 0.3 * h.get(3)) as f64 * c,
                );
                let r = (0.12 + 0.2 * h.get(4)) as f64 * c;
                let d = ((x - cx).powi(2) + (y - cy).powi(2)).sqrt();
                ((r - d) / w + 0.5).clamp(0.0, 1.0) as f32
            } else {
                let st = 1.0 + (lv.stretch - 1.0).max(0.0) * h.get(5);
                let wx = ((0.25 + 0.45 * h.get(6)) * st).min(0.9) as f64 * c;
                let wy = ((0.25 + 0.45 * h.get(7)) / st).max(0.08) as f64 * c;
                let x0 = 0.05 * c + (0.9 * c - wx) * h.get(8) as f64;
                let y0 = 0.05 * c + (0.9 * c - wy) * h.get(9) as f64;
                let outer = cov1(x, x0, x0 + wx, w) * cov1(y, y0, y0 + wy, w);
                if h.get(10) < lv.frame {
                    let t = 0.18 * wx.min(wy);
                    outer - cov1(x, x0 + t, x0 + wx - t, w) * cov1(y, y0 + t, y0 + wy - t, w)
                } else {
                    outer
                }
            };
            if cov > 0.0 {
                let sc = shape_colour(&h, lightness(col), lv.contrast);
                col = lerp3(col, sc, cov * fade);
            }
        }
        if let Some((bw, bc, size)) = self.border {
            let inside = cov1(u, bw, size[0] - bw, w) * cov1(v, bw, size[1] - bw, w);
            col = lerp3(bc, col, inside);
        }
        col
    }

    fn with(seed: u64, base_l: f32, tint: f32, levels: Vec<Level>) -> Self {
        let h = mix(seed ^ 0x5EED);
        let t = [unit(h, 1) - 0.5, unit(h, 2) - 0.5, unit(h, 3) - 0.5];
        let base = [
            (base_l * (1.0 + tint * t[0])).clamp(0.0, 1.0),
            (base_l * (1.0 + tint * t[1])).clamp(0.0, 1.0),
            (base_l * (1.0 + tint * t[2])).clamp(0.0, 1.0),
        ];
        Self {
            seed,
            base,
            levels,
            border: None,
        }
    }

    /// Scale factor in [0.8, 1.25) so that two textures never share cell grids.
    fn jitter(seed: u64, k: u64) -> f64 {
        0.8 + 0.45 * unit(mix(seed), k) as f64
    }

    /// Walls: large panels, medium shapes, small details; medium contrast.
    pub fn wall(seed: u64) -> Self {
        let j = |k| Self::jitter(seed, k);
        let l = 0.45 + 0.3 * unit(mix(seed), 9);
        Self::with(
            seed,
            l,
            0.5,
            vec![
                Level {
                    cell: 0.9 * j(1),
                    density: 0.6,
                    disc: 0.1,
                    frame: 0.3,
                    stretch: 1.5,
                    contrast: 0.3,
                },
                Level {
                    cell: 0.33 * j(2),
                    density: 0.55,
                    disc: 0.25,
                    frame: 0.25,
                    stretch: 1.3,
                    contrast: 0.45,
                },
                Level {
                    cell: 0.13 * j(3),
                    density: 0.5,
                    disc: 0.2,
                    frame: 0.1,
                    stretch: 1.0,
                    contrast: 0.5,
                },
                Level {
                    cell: 0.055 * j(4),
                    density: 0.35,
                    disc: 0.2,
                    frame: 0.0,
                    stretch: 1.0,
                    contrast: 0.4,
                },
            ],
        )
    }

    /// Floors: elongated planks and tiles plus fine speckle.
    pub fn floor(seed: u64) -> Self {
        let j = |k| Self::jitter(seed, k);
        Self::with(
            seed,
            0.35 + 0.2 * unit(mix(seed), 9),
            0.6,
            vec![
                Level {
                    cell: 0.6 * j(1),
                    density: 0.7,
                    disc: 0.0,
                    frame: 0.2,
                    stretch: 3.0,
                    contrast: 0.3,
                },
                Level {
                    cell: 0.2 * j(2),
                    density: 0.5,
                    disc: 0.15,
                    frame: 0.2,
                    stretch: 2.0,
                    contrast: 0.4,
                },
                Level {
                    cell: 0.07 * j(3),
                    density: 0.45,
                    disc: 0.3,
                    frame: 0.0,
                    stretch: 1.0,
                    contrast: 0.45,
                },
            ],
        )
    }

    /// Ceilings: bright panels, lamps and vents; a low robot camera sees a lot of ceiling, so it
    /// must carry features too.
    pub fn ceiling(seed: u64) -> Self {
        let j = |k| Self::jitter(seed, k);
        Self::with(
            seed,
            0.8,
            0.1,
            vec![
                Level {
                    cell: 0.6 * j(1),
                    density: 0.6,
                    disc: 0.3,
                    frame: 0.6,
                    stretch: 1.0,
                    contrast: 0.45,
                },
                Level {
                    cell: 0.2 * j(2),
                    density: 0.5,
                    disc: 0.3,
                    frame: 0.2,
                    stretch: 1.5,
                    contrast: 0.5,
                },
                Level {
                    cell: 0.08 * j(3),
                    density: 0.4,
                    disc: 0.3,
                    frame: 0.0,
                    stretch: 1.0,
                    contrast: 0.45,
                },
            ],
        )
    }

    /// Furniture: saturated bases with strong small-scale structure (books, handles, labels).
    pub fn furniture(seed: u64) -> Self {
        let j = |k| Self::jitter(seed, k);
        Self::with(
            seed,
            0.25 + 0.5 * unit(mix(seed), 9),
            1.0,
            vec![
                Level {
                    cell: 0.3 * j(1),
                    density: 0.7,
                    disc: 0.1,
                    frame: 0.4,
                    stretch: 1.8,
                    contrast: 0.5,
                },
                Level {
                    cell: 0.1 * j(2),
                    density: 0.6,
                    disc: 0.3,
                    frame: 0.1,
                    stretch: 1.0,
                    contrast: 0.55,
                },
                Level {
                    cell: 0.04 * j(3),
                    density: 0.4,
                    disc: 0.2,
                    frame: 0.0,
                    stretch: 1.0,
                    contrast: 0.4,
                },
            ],
        )
    }

    /// Door frames: plain, slightly darker than walls, a few marks.
    pub fn frame(seed: u64) -> Self {
        Self::with(
            seed,
            0.3,
            0.3,
            vec![Level {
                cell: 0.12,
                density: 0.3,
                disc: 0.5,
                frame: 0.0,
                stretch: 1.0,
                contrast: 0.4,
            }],
        )
    }

    /// Posters: light background, dense high-contrast content and a dark border of 3 cm.
    pub fn poster(seed: u64, size: [f64; 2]) -> Self {
        let j = |k| Self::jitter(seed, k);
        let mut t = Self::with(
            seed,
            0.85,
            0.2,
            vec![
                Level {
                    cell: 0.2 * j(1),
                    density: 0.8,
                    disc: 0.3,
                    frame: 0.3,
                    stretch: 1.5,
                    contrast: 0.7,
                },
                Level {
                    cell: 0.07 * j(2),
                    density: 0.7,
                    disc: 0.3,
                    frame: 0.1,
                    stretch: 1.0,
                    contrast: 0.7,
                },
                Level {
                    cell: 0.03 * j(3),
                    density: 0.4,
                    disc: 0.2,
                    frame: 0.0,
                    stretch: 1.0,
                    contrast: 0.6,
                },
            ],
        );
        t.border = Some((POSTER_BORDER, POSTER_BORDER_COLOUR, size));
        t
    }
}

/// Width of a poster's border in metres.
pub const POSTER_BORDER: f64 = 0.03;
/// Colour of a poster's border (near black).
pub const POSTER_BORDER_COLOUR: [f32; 3] = [0.06, 0.05, 0.05];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sampling_is_deterministic_and_seed_dependent() {
        let a = Texture::wall(1);
        let b = Texture::wall(2);
        let mut differ = 0;
        for k in 0..200 {
            let (u, v) = (k as f64 * 0.037, k as f64 * 0.021);
            assert_eq!(a.sample(u, v, 0.002), Texture::wall(1).sample(u, v, 0.002));
            if a.sample(u, v, 0.002) != b.sample(u, v, 0.002) {
                differ += 1;
            }
        }
        assert!(differ > 100, "only {differ} samples differ");
    }
}
