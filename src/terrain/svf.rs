//! The sky-view factor (SPEC §3.7 `svf`) from the horizons at `bins` azimuths.
//!
//! - `radiative`: mean_n cos² α_n = mean_n (1 − sin² α_n), the share of isotropic diffuse sky
//!   light a horizontal surface receives (Dozier & Frew 1990, slope 0).
//! - `visual`: 1 − mean_n sin α_n (Zakšek, Oštir & Kokalj 2011, as RVT computes it).
//! - `tilted`: the share of isotropic diffuse sky light on the tilted surface itself (Dozier &
//!   Frew 1990, the equation for a slope): (1/2π) ∫ [cos S sin² H_φ + sin S cos(φ − A) (H_φ −
//!   sin H_φ cos H_φ)] dφ with H_φ the zenith angle of the higher of the horizon and the
//!   surface's own plane. That is (1/π) ∫ V max(0, n·ω) dω over the sky above the horizon,
//!   exactly the AO of SPEC §3.8, so [`svf_tilted`] is [`crate::terrain::surface`]'s closed
//!   form at the bins; the terrain test holds it to D&F's equation computed by numpy.

use crate::params::SvfModel;
use crate::terrain::surface::{occlusion_fast, BinDirs};

/// The tilted surface's sky-view factor of one texel from its per-bin sin α (`dirs` of as many
/// bins) and its unit normal `n` in the tangent frame.
#[inline]
pub fn svf_tilted(s: &[f32], n: [f64; 3], dirs: &BinDirs) -> f32 {
    occlusion_fast(s, n, dirs).ao as f32
}

/// What bin sin α = `v` takes from the sky of a surface facing straight up: sin² α
/// (`radiative`: the sky left is cos² α = 1 − sin² α) or sin α (`visual`), `v` clamped to [0, 1].
///
/// Both ways a bake gets its horizons sum these in f32 in the bins' order, [`svf`] over a texel's
/// bins and `sweep`'s planes one bin at a time into a plane of sums (4 bytes a texel, where an
/// f64 sum took 8: 268 MB at 8192²), so the two give the same bits. The blocked share is summed
/// rather than the sky's: it is small where the sky is open, so the f32 sum's rounding is
/// relative to it, and at most 1e-5 of the factor at 720 bins (a test holds it against f64).
#[inline]
pub fn blocked(v: f32, model: SvfModel) -> f32 {
    let v = v.clamp(0.0, 1.0);
    match model {
        // A surface facing straight up (the tilted model of a flat texel) is `radiative`.
        SvfModel::Radiative | SvfModel::Tilted => v * v,
        SvfModel::Visual => v,
    }
}

/// The sky-view factor from the f32 sum of [`blocked`] over `bins` bins (1 for none).
#[inline]
pub fn from_blocked(sum: f32, bins: usize) -> f32 {
    if bins == 0 {
        return 1.0;
    }
    (1.0 - f64::from(sum) / bins as f64) as f32
}

/// The sky-view factor of one texel from its per-bin sin α, for a surface facing straight up
/// (`tilted` needs the normal: [`svf_tilted`]).
#[inline]
pub fn svf(s: &[f32], model: SvfModel) -> f32 {
    from_blocked(s.iter().fold(0.0f32, |a, &v| a + blocked(v, model)), s.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn open_sky_and_walls() {
        assert_eq!(svf(&[0.0; 16], SvfModel::Radiative), 1.0);
        assert_eq!(svf(&[0.0; 16], SvfModel::Visual), 1.0);
        // Half the azimuths at 30°: cos² 30° = 0.75, sin 30° = 0.5.
        let s = [0.5, 0.0, 0.5, 0.0];
        assert!((svf(&s, SvfModel::Radiative) - 0.875).abs() < 1e-6);
        assert!((svf(&s, SvfModel::Visual) - 0.75).abs() < 1e-6);
    }

    #[test]
    fn the_f32_sum_stays_within_1e_5_of_an_f64_sum_at_720_bins() {
        // Random horizons, open to nearly closed, and the extremes: closed exactly 0, open 1.
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 40) as f32 / (1u64 << 24) as f32
        };
        let mut worst = 0.0f64;
        for case in 0..400 {
            let top = (case % 10) as f32 / 9.0;
            let s: Vec<f32> = (0..720).map(|_| next() * top).collect();
            for model in [SvfModel::Radiative, SvfModel::Visual] {
                let f64_sum: f64 = s
                    .iter()
                    .map(|&v| match model {
                        SvfModel::Visual => 1.0 - f64::from(v),
                        _ => 1.0 - f64::from(v).powi(2),
                    })
                    .sum();
                let want = f64_sum / 720.0;
                worst = worst.max((f64::from(svf(&s, model)) - want).abs());
            }
        }
        assert!(worst < 1e-5, "f32 sums off by {worst:e}");
        assert!(worst > 0.0, "the test's maps never rounded: it checks nothing");
        assert_eq!(svf(&[1.0; 720], SvfModel::Radiative), 0.0);
        assert_eq!(svf(&[1.0; 720], SvfModel::Visual), 0.0);
        assert_eq!(svf(&[0.0; 720], SvfModel::Radiative), 1.0);
        assert_eq!(svf(&[], SvfModel::Visual), 1.0);
    }

    #[test]
    fn tilted_is_radiative_when_flat_and_cos_half_angle_squared_on_an_open_slope() {
        let s = [0.5f32, 0.1, 0.3, 0.0, 0.7, 0.2, 0.0, 0.4];
        let dirs = BinDirs::new(8);
        let flat = svf_tilted(&s, [0.0, 0.0, 1.0], &dirs);
        assert!((flat - svf(&s, SvfModel::Radiative)).abs() < 1e-5, "{flat}");
        // An open plane tilted by S toward +x (no terrain above the horizontal): D&F's
        // equation with H_φ the zenith angle of the plane's own horizon where it rises above
        // the horizontal (upslope), 90° elsewhere (α ≥ 0), at 3600 azimuths.
        let slope = 30f64.to_radians();
        let n = [slope.sin(), 0.0, slope.cos()];
        let bins = 3600;
        let got = svf_tilted(&vec![0.0; bins], n, &BinDirs::new(bins)) as f64;
        let mut want = 0.0;
        for k in 0..bins {
            let phi = k as f64 * std::f64::consts::TAU / bins as f64;
            // The plane's own horizon (zenith angle) where it rises above the horizontal.
            let rise = (-slope.tan() * phi.cos()).atan().max(0.0);
            let h = std::f64::consts::FRAC_PI_2 - rise;
            want +=
                slope.cos() * h.sin().powi(2) + slope.sin() * phi.cos() * (h - h.sin() * h.cos());
        }
        want /= bins as f64;
        assert!((got - want).abs() < 1e-4, "{got} vs {want}");
    }
}
