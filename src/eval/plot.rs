//! The evaluation plot: top view of ground truth vs the aligned estimate, and the ATE error over
//! time. Rendered into memory with plotters and written atomically as PNG. The font is shipped
//! (DejaVu Sans, see fonts/LICENSE-DejaVu.txt) so plots need nothing from the system.

use super::{Associated, AteResult};
use crate::error::{Error, Result};
use crate::io::{atomic_write, tum::StampedPose};
use nalgebra::{Matrix3, Vector3};
use plotters::prelude::*;
use std::path::Path;
use std::sync::Once;

const FONT: &[u8] = include_bytes!("fonts/DejaVuSans.ttf");
const W: u32 = 1400;
const H: u32 = 600;

pub(crate) fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // Only fails on an invalid font, which the shipped one is not.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

/// The plane of largest spread of the ground truth (its first two principal axes), so that the
/// "top view" is meaningful whatever the world frame's up axis is.
pub(crate) fn principal_axes(
    points: &[Vector3<f64>],
) -> (Vector3<f64>, Vector3<f64>, Vector3<f64>) {
    let n = points.len().max(1) as f64;
    let mean = points.iter().sum::<Vector3<f64>>() / n;
    let mut cov = Matrix3::zeros();
    for p in points {
        let d = p - mean;
        cov += d * d.transpose();
    }
    let eig = cov.symmetric_eigen();
    let mut idx = [0usize, 1, 2];
    idx.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let a1: Vector3<f64> = eig.eigenvectors.column(idx[0]).into();
    let a2: Vector3<f64> = eig.eigenvectors.column(idx[1]).into();
    (mean, a1, a2)
}

pub(crate) fn padded_range(v: impl Iterator<Item = f64> + Clone) -> std::ops::Range<f64> {
    let lo = v.clone().fold(f64::INFINITY, f64::min);
    let hi = v.fold(f64::NEG_INFINITY, f64::max);
    let (lo, hi) = if lo.is_finite() { (lo, hi) } else { (0.0, 1.0) };
    let pad = ((hi - lo) * 0.05).max(1e-3);
    (lo - pad)..(hi + pad)
}

/// Widens one of the ranges so that a metre is as long on both axes of a `aspect` (w/h) panel.
pub(crate) fn equal_aspect(
    x: std::ops::Range<f64>,
    y: std::ops::Range<f64>,
    aspect: f64,
) -> (std::ops::Range<f64>, std::ops::Range<f64>) {
    let (w, h) = (x.end - x.start, y.end - y.start);
    let grow = |r: std::ops::Range<f64>, len: f64| {
        let c = 0.5 * (r.start + r.end);
        (c - 0.5 * len)..(c + 0.5 * len)
    };
    if w / h < aspect {
        (grow(x, h * aspect), y)
    } else {
        (x, grow(y, w / aspect))
    }
}

/// Draws the evaluation plot. `gt` is the full ground truth (drawn as the reference path).
pub fn plot_ate(
    path: &Path,
    gt: &[StampedPose],
    assoc: &Associated,
    ate: &AteResult,
    title: &str,
) -> Result<()> {
    register_font();
    let mut buf = vec![0u8; (W * H * 3) as usize];
    let draw_err = |e: &dyn std::fmt::Display| Error::file(path, format!("cannot draw plot: {e}"));
    {
        let root = BitMapBackend::with_buffer(&mut buf, (W, H)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| draw_err(&e))?;
        let root = root
            .titled(title, ("sans-serif", 22))
            .map_err(|e| draw_err(&e))?;
        let (left, right) = root.split_horizontally(W / 2);

        let gtp: Vec<Vector3<f64>> = gt.iter().map(|p| p.pose.translation.vector).collect();
        let (mean, a1, a2) = principal_axes(&gtp);
        let proj = |p: &Vector3<f64>| ((p - mean).dot(&a1), (p - mean).dot(&a2));
        let gt2: Vec<(f64, f64)> = gtp.iter().map(proj).collect();
        let est2: Vec<(f64, f64)> = assoc
            .estimate
            .iter()
            .map(|p| proj(&p.translation.vector))
            .collect();
        let all = gt2.iter().chain(&est2);
        let (xr, yr) = equal_aspect(
            padded_range(all.clone().map(|p| p.0)),
            padded_range(all.map(|p| p.1)),
            (W / 2 - 75) as f64 / (H - 110) as f64,
        );
        let mut c = ChartBuilder::on(&left)
            .caption(
                "top view (principal plane of the ground truth)",
                ("sans-serif", 16),
            )
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(55)
            .build_cartesian_2d(xr, yr)
            .map_err(|e| draw_err(&e))?;
        c.configure_mesh()
            .x_desc("axis 1 [m]")
            .y_desc("axis 2 [m]")
            .draw()
            .map_err(|e| draw_err(&e))?;
        c.draw_series(LineSeries::new(gt2, BLACK.stroke_width(2)))
            .map_err(|e| draw_err(&e))?
            .label("ground truth")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
        // Estimate as points: it may have gaps (lost tracking, dropped frames).
        c.draw_series(est2.iter().map(|&p| Circle::new(p, 2, BLUE.filled())))
            .map_err(|e| draw_err(&e))?
            .label(format!("estimate ({:?}-aligned)", ate.alignment).to_lowercase())
            .legend(|(x, y)| Circle::new((x + 10, y), 3, BLUE.filled()));
        c.configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| draw_err(&e))?;

        let t0 = assoc.t.first().copied().unwrap_or(0.0);
        let errs: Vec<(f64, f64)> = ate.errors.iter().map(|&(t, e)| (t - t0, e)).collect();
        let tr = padded_range(errs.iter().map(|p| p.0));
        let emax = errs.iter().map(|p| p.1).fold(0.0, f64::max).max(1e-6) * 1.1;
        let mut c = ChartBuilder::on(&right)
            .caption(
                format!(
                    "ATE: RMSE {:.4} m, median {:.4} m, max {:.4} m ({} poses)",
                    ate.stats.rmse, ate.stats.median, ate.stats.max, ate.pairs
                ),
                ("sans-serif", 16),
            )
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(65)
            .build_cartesian_2d(tr, 0.0..emax)
            .map_err(|e| draw_err(&e))?;
        c.configure_mesh()
            .x_desc("time since first pose [s]")
            .y_desc("translational error [m]")
            .draw()
            .map_err(|e| draw_err(&e))?;
        c.draw_series(LineSeries::new(errs, RED.stroke_width(2)))
            .map_err(|e| draw_err(&e))?;
        c.draw_series(std::iter::once(PathElement::new(
            vec![
                (c.x_range().start, ate.stats.rmse),
                (c.x_range().end, ate.stats.rmse),
            ],
            BLACK.stroke_width(1),
        )))
        .map_err(|e| draw_err(&e))?;
        root.present().map_err(|e| draw_err(&e))?;
    }
    let img = image::RgbImage::from_raw(W, H, buf).expect("buffer has W*H*3 bytes");
    let mut png = std::io::Cursor::new(Vec::new());
    image::DynamicImage::ImageRgb8(img)
        .write_to(&mut png, image::ImageFormat::Png)
        .map_err(|e| Error::file(path, format!("cannot encode PNG: {e}")))?;
    atomic_write(path, png.get_ref())
}
