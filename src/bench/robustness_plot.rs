//! The robustness benchmark's plot: per sequence, the coverage of the final largest map under
//! each kidnapping setting, one bar per controller — where a controller loses the map after a
//! kidnapping, its bar drops. Written with plotters as PNG (the shipped font, atomically).

use crate::error::{Error, Result};
use crate::eval::plot::register_font;
use plotters::prelude::*;
use std::path::Path;

/// One cell of the plot: (sequence, perturbation, controller, coverage in 0..1).
pub type CoverageRow = (String, String, String, Option<f64>);

const W: u32 = 1400;
const PANEL_H: u32 = 330;
const COLOURS: [RGBColor; 4] = [
    RGBColor(0, 90, 181),
    RGBColor(220, 120, 0),
    RGBColor(0, 150, 70),
    RGBColor(150, 150, 150),
];

/// Reads the plot's columns from a robustness.csv (sequence, perturbation, controller and
/// coverage come before the only quoted fields, the command and the error).
pub fn read_csv(path: &Path) -> Result<Vec<CoverageRow>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::file(path, e.to_string()))?;
    let mut lines = text.lines().enumerate();
    let header: Vec<&str> = lines
        .next()
        .map(|(_, l)| l.split(',').collect())
        .unwrap_or_default();
    let col = |name: &str| {
        header.iter().position(|h| *h == name).ok_or_else(|| {
            Error::file(
                path,
                format!("line 1: no column '{name}' (not a robustness.csv)"),
            )
        })
    };
    let (s, p, c, cov) = (
        col("sequence")?,
        col("perturbation")?,
        col("controller")?,
        col("coverage")?,
    );
    let mut rows = Vec::new();
    for (i, line) in lines {
        let f: Vec<&str> = line.splitn(cov + 2, ',').collect();
        if f.len() <= cov {
            return Err(Error::file(path, format!("line {}: too few fields", i + 1)));
        }
        let coverage = if f[cov].is_empty() {
            None
        } else {
            Some(f[cov].parse::<f64>().map_err(|e| {
                Error::file(path, format!("line {}: coverage '{}': {e}", i + 1, f[cov]))
            })?)
        };
        rows.push((
            f[s].to_string(),
            f[p].to_string(),
            f[c].to_string(),
            coverage,
        ));
    }
    Ok(rows)
}

/// Draws the kidnapping rows of `rows` into `path` (nothing when there are none).
pub fn plot_coverage(path: &Path, rows: &[CoverageRow]) -> Result<bool> {
    let kidnap: Vec<&CoverageRow> = rows.iter().filter(|r| r.1.starts_with("kidnap-")).collect();
    let mut seqs: Vec<&str> = Vec::new();
    let mut ctrls: Vec<&str> = Vec::new();
    for r in &kidnap {
        if !seqs.contains(&r.0.as_str()) {
            seqs.push(&r.0);
        }
        if !ctrls.contains(&r.2.as_str()) {
            ctrls.push(&r.2);
        }
    }
    if seqs.is_empty() {
        return Ok(false);
    }
    register_font();
    let h = PANEL_H * seqs.len() as u32 + 40;
    let mut buf = vec![0u8; (W * h * 3) as usize];
    let draw_err = |e: &dyn std::fmt::Display| Error::file(path, format!("cannot draw plot: {e}"));
    {
        let root = BitMapBackend::with_buffer(&mut buf, (W, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| draw_err(&e))?;
        let root = root
            .titled(
                "Coverage of the final largest map after kidnapping (frames posed in it, %)",
                ("sans-serif", 22),
            )
            .map_err(|e| draw_err(&e))?;
        let panels = root.split_evenly((seqs.len(), 1));
        for (panel, seq) in panels.iter().zip(&seqs) {
            let mut perts: Vec<&str> = Vec::new();
            for r in kidnap.iter().filter(|r| r.0 == *seq) {
                if !perts.contains(&r.1.as_str()) {
                    perts.push(&r.1);
                }
            }
            let n = perts.len();
            let mut c = ChartBuilder::on(panel)
                .caption(*seq, ("sans-serif", 18))
                .margin(8)
                .x_label_area_size(30)
                .y_label_area_size(45)
                .build_cartesian_2d(0.0..n as f64, 0.0..100.0)
                .map_err(|e| draw_err(&e))?;
            c.configure_mesh()
                .disable_x_mesh()
                .x_labels(n.max(1) * 2 + 1)
                .x_label_formatter(&|x| {
                    let i = x.floor() as usize;
                    if (x - i as f64 - 0.5).abs() < 1e-6 && i < n {
                        perts[i].trim_start_matches("kidnap-").to_string()
                    } else {
                        String::new()
                    }
                })
                .y_desc("coverage [%]")
                .draw()
                .map_err(|e| draw_err(&e))?;
            let width = 0.8 / ctrls.len() as f64;
            for (k, ctrl) in ctrls.iter().enumerate() {
                let colour = COLOURS[k % COLOURS.len()];
                let bars = perts.iter().enumerate().filter_map(|(i, p)| {
                    let cov = kidnap
                        .iter()
                        .find(|r| r.0 == *seq && r.1 == *p && r.2 == *ctrl)?
                        .3?;
                    let x0 = i as f64 + 0.1 + k as f64 * width;
                    Some(Rectangle::new(
                        [(x0, 0.0), (x0 + width * 0.9, 100.0 * cov)],
                        colour.filled(),
                    ))
                });
                c.draw_series(bars)
                    .map_err(|e| draw_err(&e))?
                    .label(*ctrl)
                    .legend(move |(x, y)| {
                        Rectangle::new([(x, y - 5), (x + 14, y + 5)], colour.filled())
                    });
            }
            c.configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .draw()
                .map_err(|e| draw_err(&e))?;
        }
        root.present().map_err(|e| draw_err(&e))?;
    }
    let img = image::RgbImage::from_raw(W, h, buf).expect("buffer has W*h*3 bytes");
    let mut png = std::io::Cursor::new(Vec::new());
    image::DynamicImage::ImageRgb8(img)
        .write_to(&mut png, image::ImageFormat::Png)
        .map_err(|e| Error::file(path, format!("cannot encode PNG: {e}")))?;
    crate::io::atomic_write(path, png.get_ref())?;
    Ok(true)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_csv_and_draws_a_png() {
        let dir = tempfile::tempdir().unwrap();
        let csv = dir.path().join("robustness.csv");
        std::fs::write(
            &csv,
            "sequence,perturbation,controller,ate_m,ate_all_m,coverage,maps,command\n\
             s,none,ours,0.01,0.01,1.0,1,\"homing run, quoted\"\n\
             s,kidnap-1x1s,ours,0.01,0.01,0.9,1,x\n\
             s,kidnap-1x1s,ldso,,,0.4,1,x\n\
             s,kidnap-1x1s,proslam,,,,0,x\n",
        )
        .unwrap();
        let rows = read_csv(&csv).unwrap();
        assert_eq!(rows.len(), 4);
        assert_eq!(rows[1].3, Some(0.9));
        assert_eq!(rows[3].3, None);
        let png = dir.path().join("p.png");
        assert!(plot_coverage(&png, &rows).unwrap());
        let img = image::open(&png).unwrap();
        assert_eq!(img.width(), W);
        // No kidnapping rows: nothing drawn.
        assert!(!plot_coverage(&png, &rows[..1]).unwrap());
        // A malformed coverage names the file and line.
        std::fs::write(
            &csv,
            "sequence,perturbation,controller,coverage\ns,none,ours,x\n",
        )
        .unwrap();
        let e = read_csv(&csv).unwrap_err().to_string();
        assert!(e.contains("line 2"), "{e}");
    }
}
