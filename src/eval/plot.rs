//! Error against time, drawn as a PNG with nothing but [`crate::encode::png`].
//!
//! A plotting crate would pull in font and system libraries for one chart; this is a few
//! rasterising loops and a 5×7 bitmap font (upper case, digits and the symbols the chart needs).
//! Two panels share the time axis (log scale): shadow error and horizon error, each point one
//! model over the whole corpus, coloured by family, with its Pareto front as a staircase.

use super::report::{pareto, Summary};
use crate::encode::png::{encode8, PngColor};
use crate::error::Result;

const W: usize = 1200;
const H: usize = 520;

/// A small RGBA canvas.
struct Canvas {
    px: Vec<u8>,
}

type Rgb = [u8; 3];

const BLACK: Rgb = [0, 0, 0];
const GRID: Rgb = [225, 225, 225];
const FRONT: Rgb = [40, 40, 40];

/// Colour of each family, also used for the legend.
pub const FAMILIES: [(&str, Rgb); 8] = [
    ("lengyel", [31, 119, 180]),
    ("exact", [214, 39, 40]),
    ("march", [23, 190, 207]),
    ("sweep", [188, 189, 34]),
    ("auto", [255, 127, 14]),
    ("storage", [44, 160, 44]),
    ("cubemap", [148, 103, 189]),
    ("fourier", [140, 86, 75]),
];

fn family_colour(f: &str) -> Rgb {
    FAMILIES.iter().find(|(n, _)| *n == f).map(|c| c.1).unwrap_or([120, 120, 120])
}

impl Canvas {
    fn new() -> Self {
        Canvas { px: vec![255; W * H * 4] }
    }
    fn set(&mut self, x: i64, y: i64, c: Rgb) {
        if x >= 0 && y >= 0 && (x as usize) < W && (y as usize) < H {
            let i = (y as usize * W + x as usize) * 4;
            self.px[i..i + 3].copy_from_slice(&c);
        }
    }
    fn rect(&mut self, x0: i64, y0: i64, x1: i64, y1: i64, c: Rgb) {
        for y in y0..=y1 {
            for x in x0..=x1 {
                self.set(x, y, c);
            }
        }
    }
    /// Bresenham, `thick` pixels wide.
    fn line(&mut self, (x0, y0): (i64, i64), (x1, y1): (i64, i64), c: Rgb, thick: i64) {
        let (dx, dy) = ((x1 - x0).abs(), -(y1 - y0).abs());
        let (sx, sy) = (if x0 < x1 { 1 } else { -1 }, if y0 < y1 { 1 } else { -1 });
        let (mut x, mut y, mut err) = (x0, y0, dx + dy);
        loop {
            self.rect(x - thick / 2, y - thick / 2, x + (thick - 1) / 2, y + (thick - 1) / 2, c);
            if x == x1 && y == y1 {
                break;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x += sx;
            }
            if e2 <= dx {
                err += dx;
                y += sy;
            }
        }
    }
    fn disc(&mut self, cx: i64, cy: i64, r: i64, c: Rgb) {
        for y in -r..=r {
            for x in -r..=r {
                if x * x + y * y <= r * r {
                    self.set(cx + x, cy + y, c);
                }
            }
        }
    }
    fn ring(&mut self, cx: i64, cy: i64, r: i64, c: Rgb) {
        for y in -r..=r {
            for x in -r..=r {
                let d = x * x + y * y;
                if d <= r * r && d > (r - 2) * (r - 2) {
                    self.set(cx + x, cy + y, c);
                }
            }
        }
    }
    /// Text with the 5×7 font at `scale`, top-left at (x, y). Returns the width drawn.
    fn text(&mut self, x: i64, y: i64, s: &str, scale: i64, c: Rgb) -> i64 {
        let mut cx = x;
        for ch in s.chars() {
            let g = glyph(ch);
            for (row, bits) in g.iter().enumerate() {
                for col in 0..5 {
                    if bits & (0x10 >> col) != 0 {
                        let (px, py) = (cx + col * scale, y + row as i64 * scale);
                        self.rect(px, py, px + scale - 1, py + scale - 1, c);
                    }
                }
            }
            cx += 6 * scale;
        }
        cx - x
    }
    /// Text rotated 90° counter-clockwise, reading bottom to top, bottom-left at (x, y).
    fn text_up(&mut self, x: i64, y: i64, s: &str, scale: i64, c: Rgb) {
        let mut cy = y;
        for ch in s.chars() {
            let g = glyph(ch);
            for (row, bits) in g.iter().enumerate() {
                for col in 0..5 {
                    if bits & (0x10 >> col) != 0 {
                        let (px, py) = (x + row as i64 * scale, cy - col * scale);
                        self.rect(px, py - scale + 1, px + scale - 1, py, c);
                    }
                }
            }
            cy -= 6 * scale;
        }
    }
}

fn text_width(s: &str, scale: i64) -> i64 {
    s.chars().count() as i64 * 6 * scale
}

/// 5×7 glyphs, one byte per row, bit 4 = leftmost column. Lower case draws as upper case.
fn glyph(c: char) -> [u8; 7] {
    match c.to_ascii_uppercase() {
        '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
        '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
        '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
        '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
        '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
        '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
        '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
        '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
        '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
        'A' => [0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'B' => [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E],
        'C' => [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E],
        'D' => [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C],
        'E' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F],
        'F' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10],
        'G' => [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F],
        'H' => [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'I' => [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E],
        'J' => [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C],
        'K' => [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11],
        'L' => [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F],
        'M' => [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11],
        'N' => [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11],
        'O' => [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'P' => [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10],
        'Q' => [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D],
        'R' => [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11],
        'S' => [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E],
        'T' => [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
        'U' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'V' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04],
        'W' => [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A],
        'X' => [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11],
        'Y' => [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04],
        'Z' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F],
        '.' => [0, 0, 0, 0, 0, 0x0C, 0x0C],
        ',' => [0, 0, 0, 0, 0x0C, 0x04, 0x08],
        '-' => [0, 0, 0, 0x1F, 0, 0, 0],
        '+' => [0, 0x04, 0x04, 0x1F, 0x04, 0x04, 0],
        '=' => [0, 0, 0x1F, 0, 0x1F, 0, 0],
        '%' => [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03],
        '(' => [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02],
        ')' => [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08],
        '/' => [0, 0x01, 0x02, 0x04, 0x08, 0x10, 0],
        ':' => [0, 0x0C, 0x0C, 0, 0x0C, 0x0C, 0],
        '°' => [0x0C, 0x12, 0x12, 0x0C, 0, 0, 0],
        _ => [0; 7],
    }
}

/// Tick values for a linear axis from 0 to `max`: a 1/2/5 step giving about 5 ticks.
fn linear_ticks(max: f64) -> (f64, Vec<f64>) {
    let raw = (max / 5.0).max(1e-12);
    let mag = 10f64.powf(raw.log10().floor());
    let step =
        [1.0, 2.0, 5.0, 10.0].iter().map(|m| m * mag).find(|s| *s >= raw).unwrap_or(mag * 10.0);
    let top = (max / step).ceil().max(1.0) * step;
    let ticks = (0..=((top / step).round() as usize)).map(|k| k as f64 * step).collect();
    (top, ticks)
}

fn fmt_tick(v: f64) -> String {
    if v == 0.0 {
        "0".into()
    } else if v >= 100.0 || v.fract() == 0.0 {
        format!("{v:.0}")
    } else if v >= 1.0 {
        format!("{v:.1}")
    } else {
        let s = format!("{v:.3}");
        s.trim_end_matches('0').to_string()
    }
}

struct Panel {
    x0: i64,
    y0: i64,
    x1: i64,
    y1: i64,
    lmin: f64,
    lmax: f64,
    ymax: f64,
}

impl Panel {
    fn px(&self, ms: f64, err: f64) -> (i64, i64) {
        let fx = (ms.max(1e-9).log10() - self.lmin) / (self.lmax - self.lmin);
        let fy = err / self.ymax;
        let x = self.x0 as f64 + fx * (self.x1 - self.x0) as f64;
        let y = self.y1 as f64 - fy * (self.y1 - self.y0) as f64;
        (x.round() as i64, y.round() as i64)
    }
}

fn panel(cv: &mut Canvas, p: &Panel, pts: &[(f64, f64, Rgb, &str)], title: &str, ylabel: &str) {
    let (top, yt) = linear_ticks(pts.iter().map(|q| q.1).fold(0.0, f64::max) * 1.05);
    let p = Panel { ymax: top, ..*p };
    for &v in &yt {
        let (_, y) = p.px(10f64.powf(p.lmin), v);
        cv.line((p.x0, y), (p.x1, y), GRID, 1);
        let s = fmt_tick(v);
        cv.text(p.x0 - 8 - text_width(&s, 1), y - 3, &s, 1, BLACK);
    }
    let mut d = p.lmin.floor() as i32;
    while (d as f64) <= p.lmax {
        for m in [1.0, 2.0, 5.0] {
            let v = m * 10f64.powi(d);
            let lv = v.log10();
            if lv < p.lmin || lv > p.lmax {
                continue;
            }
            let (x, _) = p.px(v, 0.0);
            cv.line((x, p.y0), (x, p.y1), GRID, 1);
            let s = fmt_tick(v);
            cv.text(x - text_width(&s, 1) / 2, p.y1 + 8, &s, 1, BLACK);
        }
        d += 1;
    }
    cv.line((p.x0, p.y1), (p.x1, p.y1), BLACK, 1);
    cv.line((p.x0, p.y0), (p.x0, p.y1), BLACK, 1);
    cv.text(p.x0, p.y0 - 24, title, 2, BLACK);
    let xl = "BAKE TIME, MS (LOG)";
    cv.text((p.x0 + p.x1) / 2 - text_width(xl, 1) / 2, p.y1 + 24, xl, 1, BLACK);
    cv.text_up(p.x0 - 52, (p.y0 + p.y1) / 2 + text_width(ylabel, 1) / 2, ylabel, 1, BLACK);
    // Pareto staircase: sorted by time, each step down to the next front point.
    let front = pareto(&pts.iter().map(|q| (q.0, q.1)).collect::<Vec<_>>());
    let mut fp: Vec<(f64, f64, &str)> =
        pts.iter().zip(&front).filter(|(_, f)| **f).map(|(q, _)| (q.0, q.1, q.3)).collect();
    fp.sort_by(|a, b| a.0.total_cmp(&b.0));
    for w in fp.windows(2) {
        let a = p.px(w[0].0, w[0].1);
        let b = p.px(w[1].0, w[1].1);
        cv.line(a, (b.0, a.1), FRONT, 2);
        cv.line((b.0, a.1), b, FRONT, 2);
    }
    for &(ms, e, c, _) in pts {
        let (x, y) = p.px(ms, e);
        cv.disc(x, y, 4, c);
    }
    // Label the front, trying four places around each point and skipping a label that would
    // overprint one already placed (the table has every name).
    let mut placed: Vec<(i64, i64, i64, i64)> = Vec::new();
    for &(ms, e, name) in &fp {
        let (x, y) = p.px(ms, e);
        cv.ring(x, y, 7, FRONT);
        let tw = text_width(name, 1);
        for (lx, ly) in [(x + 9, y - 14), (x + 9, y + 8), (x - 9 - tw, y - 14), (x - 9 - tw, y + 8)]
        {
            let r = (lx - 2, ly - 2, lx + tw + 2, ly + 9);
            let free = placed.iter().all(|q| r.2 < q.0 || r.0 > q.2 || r.3 < q.1 || r.1 > q.3);
            if free && lx >= 0 && lx + tw < W as i64 {
                cv.text(lx, ly, name, 1, FRONT);
                placed.push(r);
                break;
            }
        }
    }
}

/// Draws the chart for per-model summaries and returns the PNG bytes.
///
/// # Errors
/// Only if the PNG encoder fails.
pub fn render(sums: &[Summary]) -> Result<Vec<u8>> {
    let mut cv = Canvas::new();
    let tmin = sums.iter().map(|s| s.ms).fold(f64::INFINITY, f64::min).max(1e-3);
    let tmax = sums.iter().map(|s| s.ms).fold(0.0, f64::max).max(tmin * 10.0);
    let (lmin, lmax) = (tmin.log10() - 0.15, tmax.log10() + 0.15);
    let shadow: Vec<(f64, f64, Rgb, &str)> = sums
        .iter()
        .map(|s| (s.ms, s.shadow_error * 100.0, family_colour(&s.family), s.model.as_str()))
        .collect();
    let horizon: Vec<(f64, f64, Rgb, &str)> = sums
        .iter()
        .map(|s| (s.ms, s.horizon_error_deg, family_colour(&s.family), s.model.as_str()))
        .collect();
    let base = Panel { x0: 80, y0: 60, x1: 560, y1: 440, lmin, lmax, ymax: 1.0 };
    panel(&mut cv, &base, &shadow, "SHADOW ERROR", "% OF TEXELS, MEAN OF 144 LIGHTS");
    let right = Panel { x0: 700, x1: 1180, ..base };
    panel(&mut cv, &right, &horizon, "HORIZON ERROR", "MEAN ABS ANGLE ERROR, DEGREES");
    let mut lx = 80;
    for (name, c) in FAMILIES {
        if sums.iter().any(|s| s.family == name) {
            cv.disc(lx, 496, 5, c);
            lx += 28 + cv.text(lx + 10, 493, name, 1, BLACK);
        }
    }
    cv.ring(lx + 6, 496, 7, FRONT);
    cv.text(lx + 18, 493, "PARETO FRONT OF EACH PANEL (ERROR VS BAKE TIME)", 1, BLACK);
    encode8(W, H, PngColor::Rgba, &cv.px)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round_and_cover() {
        let (top, t) = linear_ticks(7.3);
        assert_eq!(top, 8.0);
        assert_eq!(t, vec![0.0, 2.0, 4.0, 6.0, 8.0]);
        let (top, t) = linear_ticks(0.042);
        assert!((top - 0.05).abs() < 1e-12 && t.len() == 6, "{top} {t:?}");
    }

    #[test]
    fn glyphs_fit_five_columns() {
        for c in "0123456789ABCDEFGHIJKLMNOPQRSTUVWXYZ.,-+=%()/:°".chars() {
            let g = glyph(c);
            assert!(g.iter().any(|&r| r != 0), "{c} is blank");
            assert!(g.iter().all(|&r| r < 0x20), "{c} is wider than 5 columns");
        }
    }
}
