//! Contact sheets: a grid of every n-th frame of a TUM folder, each labelled with its frame
//! index (white, top left) and, when `scenario.json` is present, its step (yellow, top right).
//! Made for looking at a whole sequence at once.

use std::path::Path;

use homing::io::tum::read_list;
use homing::{Error, Result};
use image::{DynamicImage, Rgb, RgbImage, imageops};

/// 3x5 bitmaps of the digits 0-9, one row per 3 bits.
const DIGITS: [[u8; 5]; 10] = [
    [7, 5, 5, 5, 7],
    [2, 6, 2, 2, 7],
    [7, 1, 7, 4, 7],
    [7, 1, 7, 1, 7],
    [5, 5, 7, 1, 1],
    [7, 4, 7, 1, 7],
    [7, 4, 7, 5, 7],
    [7, 1, 1, 1, 1],
    [7, 5, 7, 5, 7],
    [7, 5, 7, 1, 7],
];

/// Draws a decimal number with a dark backing box; `scale` pixels per font pixel.
pub fn draw_number(img: &mut RgbImage, x0: u32, y0: u32, n: usize, scale: u32, colour: Rgb<u8>) {
    let s = n.to_string();
    let (w, h) = (s.len() as u32 * 4 * scale + scale, 7 * scale);
    for y in y0..(y0 + h).min(img.height()) {
        for x in x0..(x0 + w).min(img.width()) {
            img.put_pixel(x, y, Rgb([0, 0, 0]));
        }
    }
    for (ci, ch) in s.bytes().enumerate() {
        let g = DIGITS[(ch - b'0') as usize];
        for (r, bits) in g.iter().enumerate() {
            for c in 0..3 {
                if bits & (4 >> c) != 0 {
                    for dy in 0..scale {
                        for dx in 0..scale {
                            let x = x0 + scale + (ci as u32 * 4 + c) * scale + dx;
                            let y = y0 + scale + r as u32 * scale + dy;
                            if x < img.width() && y < img.height() {
                                img.put_pixel(x, y, colour);
                            }
                        }
                    }
                }
            }
        }
    }
}

/// Step number of each frame from `scenario.json`, if the folder has one.
fn frame_steps(dir: &Path, n: usize) -> Vec<Option<usize>> {
    let mut out = vec![None; n];
    let Ok(text) = std::fs::read_to_string(dir.join("scenario.json")) else {
        return out;
    };
    let Ok(v) = serde_json::from_str::<serde_json::Value>(&text) else {
        return out;
    };
    for st in v["steps"].as_array().into_iter().flatten() {
        let (Some(s), Some(a), Some(b)) = (
            st["step"].as_u64(),
            st["first_frame"].as_u64(),
            st["last_frame"].as_u64(),
        ) else {
            continue;
        };
        for f in out
            .iter_mut()
            .take((b as usize + 1).min(n))
            .skip(a as usize)
        {
            *f = Some(s as usize);
        }
    }
    out
}

/// Builds the contact sheet of the TUM folder `dir`.
pub fn contact_sheet(
    dir: &Path,
    every: usize,
    thumb_width: u32,
    columns: usize,
) -> Result<RgbImage> {
    if every == 0 || columns == 0 || thumb_width < 16 {
        return Err(Error::Invalid(
            "--every and --columns must be at least 1, the thumbnail width at least 16".into(),
        ));
    }
    let list = read_list(&dir.join("rgb.txt"))?;
    if list.is_empty() {
        return Err(Error::file(&dir.join("rgb.txt"), "lists no images"));
    }
    let steps = frame_steps(dir, list.len());
    let picked: Vec<usize> = (0..list.len()).step_by(every).collect();
    let mut thumbs = Vec::with_capacity(picked.len());
    for &i in &picked {
        let path = dir.join(&list[i].file);
        let img = image::open(&path)
            .map_err(|e| Error::file(&path, format!("cannot read image: {e}")))?;
        let th = (img.height() as f64 * thumb_width as f64 / img.width() as f64)
            .round()
            .max(1.0) as u32;
        let mut t = imageops::resize(
            &img.to_rgb8(),
            thumb_width,
            th,
            imageops::FilterType::Triangle,
        );
        let scale = (thumb_width / 80).max(1);
        draw_number(&mut t, 0, 0, i, scale, Rgb([255, 255, 255]));
        if let Some(s) = steps[i] {
            let x = thumb_width.saturating_sub((s.to_string().len() as u32 * 4 + 1) * scale);
            draw_number(&mut t, x, 0, s, scale, Rgb([255, 220, 0]));
        }
        thumbs.push(t);
    }
    let th = thumbs[0].height();
    let rows = picked.len().div_ceil(columns);
    let gap = 2;
    let cols = columns.min(picked.len()) as u32;
    let mut sheet = RgbImage::from_pixel(
        cols * (thumb_width + gap),
        rows as u32 * (th + gap),
        Rgb([40, 40, 40]),
    );
    for (k, t) in thumbs.iter().enumerate() {
        let (c, r) = ((k % columns) as u32, (k / columns) as u32);
        imageops::replace(
            &mut sheet,
            t,
            (c * (thumb_width + gap)) as i64,
            (r * (th + gap)) as i64,
        );
    }
    Ok(sheet)
}

/// Writes a contact sheet as PNG.
pub fn write_contact_sheet(
    dir: &Path,
    every: usize,
    thumb_width: u32,
    columns: usize,
    out: &Path,
) -> Result<()> {
    let sheet = contact_sheet(dir, every, thumb_width, columns)?;
    homing::io::tum::save_png(out, &DynamicImage::ImageRgb8(sheet))
}
