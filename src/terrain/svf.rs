//! The sky-view factor (SPEC §3.7 `svf`) from the horizons at `bins` azimuths.
//!
//! - `radiative`: mean_n cos² α_n = mean_n (1 − sin² α_n), the share of isotropic diffuse sky
//!   light a horizontal surface receives (Dozier & Frew 1990, slope 0).
//! - `visual`: 1 − mean_n sin α_n (Zakšek, Oštir & Kokalj 2011, as RVT computes it).

use crate::params::SvfModel;

/// The sky-view factor of one texel from its per-bin sin α.
#[inline]
pub fn svf(s: &[f32], model: SvfModel) -> f32 {
    if s.is_empty() {
        return 1.0;
    }
    let n = s.len() as f64;
    let sum: f64 = match model {
        SvfModel::Radiative => s.iter().map(|&v| 1.0 - (v as f64).clamp(0.0, 1.0).powi(2)).sum(),
        SvfModel::Visual => s.iter().map(|&v| 1.0 - (v as f64).clamp(0.0, 1.0)).sum(),
    };
    (sum / n) as f32
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
}
