//! The far field's geometry: per azimuth, which axis is major, the slope along the minor axis,
//! the lines' step in texels of arc and where the lines of a family start ([`Lines`]); which
//! azimuths share their sweeps with the opposite one ([`azimuth_lines`], [`Lines::mirror`]).

use super::*;

/// One azimuth's line geometry (see the module doc).
#[derive(Debug, Clone, Copy)]
pub struct Lines {
    /// The major axis is x (image columns) rather than y.
    pub major_x: bool,
    /// +1 if the look direction increases the major image coordinate, −1 otherwise.
    pub sign: i64,
    /// Minor-axis image coordinate change per major step.
    pub m: f64,
    /// Arc length per major step, √(1 + m²).
    pub step: f64,
    /// Where the lines are anchored: look-order position u lies on column `at.0 + at.1·u` of
    /// the lines, which pass at minor k/SUB + i + m·at.1·column (family k, line i). (0, 1) for
    /// an azimuth of its own; a [`Lines::mirror`] reads another azimuth's lines backwards.
    pub at: (i64, i64),
}

impl Lines {
    /// The lines of image direction `d` (unit vector).
    pub fn new(d: (f64, f64)) -> Lines {
        let (dx, dy) = d;
        let major_x = dx.abs() >= dy.abs();
        let (a, b) = if major_x { (dx, dy) } else { (dy, dx) };
        let m = b / a.abs();
        let sign = if a < 0.0 { -1 } else { 1 };
        Lines { major_x, sign, m, step: (1.0 + m * m).sqrt(), at: (0, 1) }
    }

    /// The lines of the opposite azimuth that are these very lines read backwards, its
    /// position 0 on position `end` of these: the sweeps of both azimuths then share every
    /// sample and their windows (see `far_field_fast`). With `edge=wrap` a texel's own column
    /// and that column plus a multiple of the major size are the same texel, so `end` may lie
    /// past the map.
    pub fn mirror(&self, end: i64) -> Lines {
        let at = (self.at.0 + self.at.1 * end, -self.at.1);
        Lines { sign: -self.sign, m: -self.m, at, ..*self }
    }

    /// The minor coordinate of line i of family k at look-order position u.
    pub fn minor(&self, k: usize, i: i64, u: f64) -> f64 {
        let (c, m) = self.column(u);
        i as f64 + (k as f64 / SUB as f64 + m * c)
    }

    /// The lines' column of look-order position u, and the minor change per column.
    #[inline]
    fn column(&self, u: f64) -> (f64, f64) {
        (self.at.0 as f64 + self.at.1 as f64 * u, self.m * self.at.1 as f64)
    }

    /// For a texel at major position u (in look order), the family k and shift so that the
    /// texel at minor coordinate b lies nearest line i = b + shift of family k.
    pub fn family(&self, u: i64) -> (usize, i64) {
        let (c, m) = self.column(u as f64);
        let kk = (-m * c * SUB as f64).round() as i64;
        (kk.rem_euclid(SUB as i64) as usize, kk.div_euclid(SUB as i64))
    }

    /// For a texel at major position u: the sub-lines just below (role 0) and above (role 1) it
    /// on the minor axis, as (family k, shift, weight): the texel at minor b lies between line
    /// b + shift of family k of each, and its far field is their tangents weighted so.
    pub fn pair(&self, u: i64) -> [(usize, i64, f64); 2] {
        let (c, m) = self.column(u as f64);
        let f = -m * c * SUB as f64;
        let kk = f.floor();
        let t = f - kk;
        let kk = kk as i64;
        let role =
            |kk: i64, wt: f64| (kk.rem_euclid(SUB as i64) as usize, kk.div_euclid(SUB as i64), wt);
        [role(kk, 1.0 - t), role(kk + 1, t)]
    }

    /// For family k at major position u: minor offset of the lower texel from the line's
    /// integer intercept i, and the lerp weight of the upper one.
    pub fn sample(&self, k: usize, u: i64) -> (i64, f64) {
        self.sample_at(k, u as f64)
    }

    /// [`Lines::sample`] at a fractional major position.
    pub fn sample_at(&self, k: usize, u: f64) -> (i64, f64) {
        let (c, m) = self.column(u);
        let z = k as f64 / SUB as f64 + m * c;
        let off = z.floor();
        (off as i64, z - off)
    }
}

/// Where every ray ends: R (clamped to what the service takes, or the map), max(W, H) for
/// `unlimited` when wrapping, or the map's edge (`None`).
pub(super) fn reach_of(grid: &Grid<'_>, radius: Option<u32>) -> Option<f64> {
    let (w, h) = (grid.width, grid.height);
    let cap = crate::params::MAX_RADIUS.max(w.max(h) as u32);
    match (radius, grid.edge) {
        (Some(r), _) => Some(f64::from(r.clamp(1, cap))),
        (None, Edge::Wrap) => Some(w.max(h) as f64),
        (None, Edge::None) => None,
    }
}

/// The image directions of the `bins` azimuths.
pub(super) fn directions(grid: &Grid<'_>, bins: usize) -> Vec<(f64, f64)> {
    let row_step = grid.row_step();
    (0..bins).map(|n| exact::direction(n as f64 * 2.0 * PI / bins as f64, row_step)).collect()
}

/// The far field's lines of each of the `bins` azimuths, as [`Sweep`] bakes them: an azimuth's
/// own ([`Lines::new`]), or, with `edge=wrap` and a window of at least N steps, for azimuth
/// n < bins/2 its own anchored a multiple of W along them and for its opposite n + bins/2 the
/// same lines read backwards ([`Lines::mirror`]; `mirror_end` picks where), so that one sweep
/// serves both (`far_field_fast`). Chosen by geometry alone, so every instruction set and
/// every path (in memory or spilled) bakes the same lines.
pub fn azimuth_lines(grid: &Grid<'_>, radius: Option<u32>, bins: u32) -> Vec<Lines> {
    let bins = bins.max(1) as usize;
    let reach = reach_of(grid, radius);
    let mut lines: Vec<Lines> = directions(grid, bins).into_iter().map(Lines::new).collect();
    if bins.is_multiple_of(2) {
        let half = bins / 2;
        for n in 0..half {
            if let Some((a, e)) = mirror_end(grid, lines[n], reach) {
                lines[n].at = (a, 1);
                lines[n + half] = lines[n].mirror(e);
            }
        }
    }
    lines
}

/// Where an azimuth's texels and its opposite's sit on the azimuth's lines so that the two
/// share their windows ([`Lines::mirror`], [`far_field_fast`]): (A, e), the azimuth's texel u
/// on column A + u and the mirror's query column 0 on position e (column A + e), or `None`
/// where that saves nothing. Only with `edge=wrap` (a texel's column plus a multiple of the
/// major size W is the same texel, so A and e + 1 are multiples of W) and a window of R' ≥ N
/// steps: the azimuth's windows start at A + u + N, the mirror's at A + J·W + u − R', so J is
/// the multiple of W nearest R' + N, and A the first multiple of W that starts no window
/// before column 0. Pairs when the shared passes cover at most 1.5·W window starts.
pub(super) fn mirror_end(grid: &Grid<'_>, lines: Lines, reach: Option<f64>) -> Option<(i64, i64)> {
    if grid.edge != Edge::Wrap {
        return None;
    }
    let r = (reach? / lines.step + 1e-9).floor() as i64;
    let d = NEAR_STEPS as i64;
    if r < d {
        return None;
    }
    let wa = (if lines.major_x { grid.width } else { grid.height }) as i64;
    let j = ((r + d) as f64 / wa as f64).round() as i64;
    let a = ((r - j * wa).max(0) + wa - 1) / wa * wa;
    let a2 = j * wa;
    let starts = (wa + d).max(a2 + wa - r) - d.min(a2 - r);
    (2 * starts <= 3 * wa).then_some((a, a2 + wa - 1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_texel_has_one_line_at_most_half_a_sub_step_away() {
        for n in 0..64 {
            let d = exact::direction(n as f64 * 2.0 * PI / 64.0, -1);
            let l = Lines::new(d);
            for u in 0..300i64 {
                let (k, shift) = l.family(u);
                for b in -3..3i64 {
                    // Line i = b + shift of family k passes at minor i + k/SUB + m·u.
                    let v = (b + shift) as f64 + k as f64 / SUB as f64 + l.m * u as f64;
                    assert!((v - b as f64).abs() <= 0.5 / SUB as f64 + 1e-9, "{n} {u} {b} {v}");
                }
            }
        }
    }
}
