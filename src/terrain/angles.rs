//! Horizon angles at every bin (SPEC §3.7 `angles`): band n is the horizon at exactly azimuth
//! n·360°/bins, no channel reduction, in `angle_unit`, counted as `azimuth_from` says.
//!
//! The kernels compute bins at φ_n = n·2π/bins counter-clockwise from +x (SPEC §2). Compass
//! bands (`north_cw`) are the same rays renumbered: compass θ clockwise from north is
//! φ = 90° − θ with `y_axis=up` (north = +y = up the image) and φ = θ − 90° with `y_axis=down`
//! (north = −y). Both are whole bins when bins is a multiple of 4 (`params` enforces it).

use crate::params::{AngleUnit, AzimuthFrom, YAxis};

/// α from sin α ∈ [0, 1] in `unit`.
#[inline]
pub fn angle(s: f32, unit: AngleUnit) -> f32 {
    let s = s.clamp(0.0, 1.0) as f64;
    match unit {
        AngleUnit::Sin => s as f32,
        AngleUnit::Radians => s.asin() as f32,
        AngleUnit::Degrees => s.asin().to_degrees() as f32,
    }
}

/// For each output band, the kernel bin it reads.
pub fn band_bins(bins: usize, from: AzimuthFrom, y_axis: YAxis) -> Vec<usize> {
    let b = bins as i64;
    (0..b)
        .map(|n| match from {
            AzimuthFrom::EastCcw => n as usize,
            AzimuthFrom::NorthCw => {
                let quarter = b / 4;
                let bin = match y_axis {
                    YAxis::Up => quarter - n,
                    YAxis::Down => n - quarter,
                };
                bin.rem_euclid(b) as usize
            }
        })
        .collect()
}

/// The azimuth of output band n in degrees, in the convention it is counted in.
pub fn band_azimuth_deg(n: usize, bins: usize) -> f64 {
    n as f64 * 360.0 / bins as f64
}

/// Writes the angles of one texel's bins `s` into `out[band]` for each band (`order` from
/// [`band_bins`]).
#[inline]
pub fn texel_angles(s: &[f32], order: &[usize], unit: AngleUnit, mut out: impl FnMut(usize, f32)) {
    for (band, &bin) in order.iter().enumerate() {
        out(band, angle(s[bin], unit));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn units() {
        assert_eq!(angle(0.5, AngleUnit::Sin), 0.5);
        assert!((angle(0.5, AngleUnit::Degrees) - 30.0).abs() < 1e-5);
        assert!((angle(1.0, AngleUnit::Radians) - std::f32::consts::FRAC_PI_2).abs() < 1e-6);
        assert_eq!(angle(-0.1, AngleUnit::Degrees), 0.0);
    }

    #[test]
    fn compass_bands_are_renumbered_bins() {
        // 8 bins, 45° apart. Compass band 0 (north) is φ = 90° (bin 2) with y up, 270° (bin 6)
        // with y down; band 2 (east) is φ = 0 in both.
        let up = band_bins(8, AzimuthFrom::NorthCw, YAxis::Up);
        assert_eq!(up, vec![2, 1, 0, 7, 6, 5, 4, 3]);
        let down = band_bins(8, AzimuthFrom::NorthCw, YAxis::Down);
        assert_eq!(down, vec![6, 7, 0, 1, 2, 3, 4, 5]);
        assert_eq!(band_bins(5, AzimuthFrom::EastCcw, YAxis::Up), vec![0, 1, 2, 3, 4]);
    }
}
