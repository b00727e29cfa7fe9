//! Sun shadows (SPEC §3.7 `shadow`): a texel is lit when the sun stands above its horizon at the
//! sun's own azimuth (one ray per texel at exactly that azimuth, never interpolated between
//! bins). A sun at or below 0° shadows everything.

/// Value of a lit texel in `shadow.tif`.
pub const LIT: u8 = 1;
/// Value of a shadowed texel.
pub const SHADOW: u8 = 0;
/// Value of a hole (the GDAL_NODATA of `shadow.tif`).
pub const NODATA: u8 = 255;

/// Whether the sun at `elevation_deg` clears a horizon of sin α = `horizon_sin`.
#[inline]
pub fn lit(horizon_sin: f64, elevation_deg: f64) -> bool {
    elevation_deg > 0.0 && elevation_deg.to_radians().sin() > horizon_sin
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sun_against_horizon() {
        assert!(lit(0.0, 0.1));
        assert!(!lit(0.0, 0.0));
        assert!(!lit(0.0, -5.0));
        assert!(!lit(0.5, 30.0));
        assert!(lit(0.5, 30.1));
    }
}
