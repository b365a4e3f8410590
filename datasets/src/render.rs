//! CPU ray caster. One ray per pixel through the pixel centre; quads are culled per frame by
//! their projected bounding box (after clipping at the near plane), then per row, so each pixel
//! only tests the few quads that can cover it. Rows run in parallel with rayon.

use nalgebra::{Isometry3, Point3, Vector3};
use rayon::prelude::*;

use crate::scene::{Scene, in_plane};

/// Pinhole intrinsics (no distortion: synthetic data is rendered undistorted).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
}

impl Intrinsics {
    /// Kinect-like intrinsics (TUM ROS default) scaled to `width` x `height`.
    pub fn kinect(width: u32, height: u32) -> Self {
        let s = width as f64 / 640.0;
        Self {
            fx: 525.0 * s,
            fy: 525.0 * s,
            cx: 319.5 * s + 0.5 * (s - 1.0),
            cy: 239.5 * s + 0.5 * (s - 1.0),
            width,
            height,
        }
    }

    /// Pixel coordinates (pixel centres at integers) of a point in the camera frame.
    pub fn project(&self, p: &Point3<f64>) -> Option<(f64, f64)> {
        if p.z <= 1e-9 {
            return None;
        }
        Some((self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy))
    }
}

/// Raw render: linear colour (0..1, before exposure), z-depth in metres (0 = no surface),
/// the quad index hit (`u32::MAX` for none) and |cos| of the incidence angle.
pub struct RenderOut {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<f32>,
    pub depth: Vec<f32>,
    pub id: Vec<u32>,
    pub cos: Vec<f32>,
}

const NEAR: f64 = 0.02;

/// Projected pixel bounding box [x0, x1] x [y0, y1] of a quad, or None if invisible.
fn screen_bbox(
    q: &crate::scene::Quad,
    k: &Intrinsics,
    w2c: &Isometry3<f64>,
    eye: &Point3<f64>,
) -> Option<[f64; 4]> {
    // Back-face: the eye must be on the side the quad faces.
    if (eye[q.axis] - q.c) * q.facing <= 0.0 {
        return None;
    }
    let (ua, va) = in_plane(q.axis);
    let mut pts: Vec<Vector3<f64>> = Vec::with_capacity(4);
    for (a, b) in [
        (q.lo[0], q.lo[1]),
        (q.hi[0], q.lo[1]),
        (q.hi[0], q.hi[1]),
        (q.lo[0], q.hi[1]),
    ] {
        let mut p = Point3::origin();
        p[q.axis] = q.c;
        p[ua] = a;
        p[va] = b;
        pts.push((w2c * p).coords);
    }
    // Clip the polygon against z >= NEAR (Sutherland-Hodgman, one plane).
    let mut clipped: Vec<Vector3<f64>> = Vec::with_capacity(8);
    for i in 0..4 {
        let (p, q2) = (pts[i], pts[(i + 1) % 4]);
        let (pin, qin) = (p.z >= NEAR, q2.z >= NEAR);
        if pin {
            clipped.push(p);
        }
        if pin != qin {
            let t = (NEAR - p.z) / (q2.z - p.z);
            clipped.push(p + (q2 - p) * t);
        }
    }
    if clipped.is_empty() {
        return None;
    }
    let mut bb = [
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    ];
    for p in &clipped {
        let x = k.fx * p.x / p.z + k.cx;
        let y = k.fy * p.y / p.z + k.cy;
        bb[0] = bb[0].min(x);
        bb[1] = bb[1].max(x);
        bb[2] = bb[2].min(y);
        bb[3] = bb[3].max(y);
    }
    let (w, h) = (k.width as f64, k.height as f64);
    if bb[1] < -1.0 || bb[0] > w || bb[3] < -1.0 || bb[2] > h {
        return None;
    }
    Some([bb[0] - 1.0, bb[1] + 1.0, bb[2] - 1.0, bb[3] + 1.0])
}

/// Renders `scene` from camera-to-world pose `pose` (TUM camera axes: x right, y down,
/// z forward).
pub fn render(scene: &Scene, k: &Intrinsics, pose: &Isometry3<f64>) -> RenderOut {
    let (w, h) = (k.width as usize, k.height as usize);
    let w2c = pose.inverse();
    let eye = Point3::from(pose.translation.vector);
    let rot = pose.rotation.to_rotation_matrix();
    let rm = rot.matrix();
    let visible: Vec<(usize, [f64; 4])> = scene
        .quads
        .iter()
        .enumerate()
        .filter_map(|(i, q)| screen_bbox(q, k, &w2c, &eye).map(|b| (i, b)))
        .collect();
    let mut out = RenderOut {
        width: k.width,
        height: k.height,
        rgb: vec![0.0; w * h * 3],
        depth: vec![0.0; w * h],
        id: vec![u32::MAX; w * h],
        cos: vec![0.0; w * h],
    };
    let o = [eye.x, eye.y, eye.z];
    let focal = 0.5 * (k.fx + k.fy);
    out.rgb
        .par_chunks_mut(w * 3)
        .zip(out.depth.par_chunks_mut(w))
        .zip(out.id.par_chunks_mut(w))
        .zip(out.cos.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (((rgb, depth), id), cosr))| {
            let yf = y as f64;
            let row: Vec<(usize, [f64; 4])> = visible
                .iter()
                .filter(|(_, b)| b[2] <= yf && yf <= b[3])
                .copied()
                .collect();
            let dy = (yf - k.cy) / k.fy;
            for x in 0..w {
                let xf = x as f64;
                let dx = (xf - k.cx) / k.fx;
                // World direction of the ray with unit z in the camera frame, so the hit
                // parameter is the z-depth directly.
                let d = [
                    rm[(0, 0)] * dx + rm[(0, 1)] * dy + rm[(0, 2)],
                    rm[(1, 0)] * dx + rm[(1, 1)] * dy + rm[(1, 2)],
                    rm[(2, 0)] * dx + rm[(2, 1)] * dy + rm[(2, 2)],
                ];
                let mut best = f64::INFINITY;
                let mut hit = usize::MAX;
                for (qi, b) in &row {
                    if xf < b[0] || xf > b[1] {
                        continue;
                    }
                    let q = &scene.quads[*qi];
                    let dn = d[q.axis];
                    if dn * q.facing >= 0.0 {
                        continue;
                    }
                    let t = (q.c - o[q.axis]) / dn;
                    if t <= NEAR || t >= best {
                        continue;
                    }
                    let (ua, va) = in_plane(q.axis);
                    let pu = o[ua] + t * d[ua];
                    let pv = o[va] + t * d[va];
                    if pu < q.lo[0] || pu > q.hi[0] || pv < q.lo[1] || pv > q.hi[1] {
                        continue;
                    }
                    best = t;
                    hit = *qi;
                }
                if hit == usize::MAX {
                    continue;
                }
                let q = &scene.quads[hit];
                let (ua, va) = in_plane(q.axis);
                let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                let cos = (d[q.axis].abs() / norm).max(1e-3);
                let range = best * norm;
                // Footprint of one pixel on the surface, stretched at grazing angles.
                let fp = range / focal / cos.max(0.2);
                let mut u = o[ua] + best * d[ua] - q.uv_origin[0];
                let mut v = o[va] + best * d[va] - q.uv_origin[1];
                if q.flip[0] {
                    u = -u;
                }
                if q.flip[1] {
                    v = -v;
                }
                let c = scene.textures[q.tex].sample(u, v, fp);
                rgb[3 * x] = c[0] * q.shade;
                rgb[3 * x + 1] = c[1] * q.shade;
                rgb[3 * x + 2] = c[2] * q.shade;
                depth[x] = best as f32;
                id[x] = hit as u32;
                cosr[x] = cos as f32;
            }
        });
    out
}
