//! The horizon profile at one point (SPEC §3.7), as PVGIS serves one: the horizon elevation in
//! degrees at `bins` azimuths, counted as `azimuth_from` says. A pure function of a horizon
//! function (sin α at a tangent-space azimuth φ in radians): one ray per azimuth, never
//! interpolated between bins.

use crate::params::{AzimuthFrom, YAxis};

/// The tangent-space azimuth φ (radians) of an azimuth `deg` counted as `from` says.
pub fn tangent_azimuth(deg: f64, from: AzimuthFrom, y_axis: YAxis) -> f64 {
    let phi = match (from, y_axis) {
        (AzimuthFrom::EastCcw, _) => deg,
        (AzimuthFrom::NorthCw, YAxis::Up) => 90.0 - deg,
        (AzimuthFrom::NorthCw, YAxis::Down) => deg - 90.0,
    };
    phi.rem_euclid(360.0).to_radians()
}

/// (azimuth in degrees, horizon elevation in degrees) at `bins` azimuths n·360°/bins.
pub fn profile(
    bins: usize,
    from: AzimuthFrom,
    y_axis: YAxis,
    horizon_sin: impl Fn(f64) -> f64,
) -> Vec<(f64, f64)> {
    profile_with(bins, |az| tangent_azimuth(az, from, y_axis), horizon_sin)
}

/// [`profile`] with the azimuth in degrees turned into φ by `to_phi` (a true azimuth through a
/// map's projection, [`crate::heightmap::north::Compass`]).
pub fn profile_with(
    bins: usize,
    to_phi: impl Fn(f64) -> f64,
    horizon_sin: impl Fn(f64) -> f64,
) -> Vec<(f64, f64)> {
    (0..bins)
        .map(|n| {
            let az = n as f64 * 360.0 / bins as f64;
            let s = horizon_sin(to_phi(az)).clamp(0.0, 1.0);
            (az, s.asin().to_degrees())
        })
        .collect()
}

/// The profile as CSV (`azimuth_deg,elevation_deg`, one line per azimuth).
pub fn to_csv(p: &[(f64, f64)]) -> String {
    let mut out = String::from("azimuth_deg,elevation_deg\n");
    for (az, el) in p {
        out.push_str(&format!("{az},{el:.6}\n"));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compass_azimuths_map_to_tangent_space() {
        let east = tangent_azimuth(90.0, AzimuthFrom::NorthCw, YAxis::Up);
        assert!(east.abs() < 1e-12);
        let north = tangent_azimuth(0.0, AzimuthFrom::NorthCw, YAxis::Up);
        assert!((north - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        // A horizon of 30° toward tangent +y only (north with y up).
        let p = profile(4, AzimuthFrom::NorthCw, YAxis::Up, |phi| {
            if (phi - std::f64::consts::FRAC_PI_2).abs() < 1e-9 {
                0.5
            } else {
                0.0
            }
        });
        assert_eq!(p.len(), 4);
        assert!((p[0].1 - 30.0).abs() < 1e-9 && p[1].1 == 0.0);
        assert!(to_csv(&p).starts_with("azimuth_deg,elevation_deg\n0,30.000000\n"));
    }
}
