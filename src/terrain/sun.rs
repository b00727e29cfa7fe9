//! The sun's position for a time and place (SPEC §3.7 `sun_time`, `latitude`, `longitude`): NREL's
//! SPA (Reda & Andreas 2003) from the `solar-positioning` crate, behind this one function, with
//! ΔT estimated from the date (Espenak & Meeus) and the refraction of a standard atmosphere at
//! 1013.25 hPa and 12 °C (pvlib's defaults), so the elevation is the apparent one a shadow sees.

use crate::error::{Error, Result};
use solar_positioning::time::JulianDate;
use solar_positioning::{delta_t, Location, RefractionCorrection, SolarPositions};

/// The sun as seen from the ground: compass azimuth (clockwise from north) and apparent
/// elevation, degrees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sun {
    pub azimuth_north_cw: f64,
    pub elevation: f64,
}

/// Parses an RFC 3339 time (`2026-06-21T12:00:00Z`, `…+02:00`, fractional seconds allowed) into
/// UTC calendar fields and the offset in minutes.
fn parse_rfc3339(t: &str) -> Option<(i32, u32, u32, u32, u32, f64, i32)> {
    let t = t.trim();
    let (date, rest) = t.split_once(['T', 't', ' '])?;
    let mut d = date.splitn(3, '-');
    let year: i32 = d.next()?.parse().ok()?;
    let month: u32 = d.next()?.parse().ok()?;
    let day: u32 = d.next()?.parse().ok()?;
    let (time, offset) = if let Some(x) = rest.strip_suffix(['Z', 'z']) {
        (x, 0)
    } else {
        let at = rest.rfind(['+', '-'])?;
        let (time, off) = rest.split_at(at);
        let sign = if off.starts_with('-') { -1 } else { 1 };
        let (oh, om) = off[1..].split_once(':')?;
        (time, sign * (oh.parse::<i32>().ok()? * 60 + om.parse::<i32>().ok()?))
    };
    let mut p = time.splitn(3, ':');
    let hour: u32 = p.next()?.parse().ok()?;
    let minute: u32 = p.next()?.parse().ok()?;
    let second: f64 = p.next()?.parse().ok()?;
    let ok = (1..=12).contains(&month)
        && (1..=31).contains(&day)
        && hour < 24
        && minute < 60
        && (0.0..61.0).contains(&second)
        && offset.abs() < 24 * 60;
    ok.then_some((year, month, day, hour, minute, second, offset))
}

/// The sun at `time` (RFC 3339) seen from `latitude`/`longitude` (degrees) at sea level.
///
/// # Errors
/// [`Error::Param`] naming `sun_time`, `latitude` or `longitude` for a value SPA cannot take.
pub fn position(time: &str, latitude: f64, longitude: f64) -> Result<Sun> {
    let (y, mo, d, h, mi, s, offset) = parse_rfc3339(time).ok_or_else(|| {
        Error::param("sun_time", format!("`{time}` is not an RFC 3339 time (2026-06-21T12:00:00Z)"))
    })?;
    if !(-90.0..=90.0).contains(&latitude) {
        return Err(Error::param("latitude", "must be between -90 and 90 degrees"));
    }
    if !(-180.0..=180.0).contains(&longitude) {
        return Err(Error::param("longitude", "must be between -180 and 180 degrees"));
    }
    let bad = |e: solar_positioning::Error| Error::param("sun_time", format!("SPA: {e}"));
    let dt = delta_t::estimate_from_date(y, mo).map_err(bad)?;
    // Local calendar fields, then the offset removed on the continuous Julian date.
    let local = JulianDate::from_utc(y, mo, d, h, mi, s, dt).map_err(bad)?;
    let jd = JulianDate::new(local.julian_date() - f64::from(offset) / 1440.0, dt).map_err(bad)?;
    position_jd(jd, latitude, longitude, "sun_time")
}

/// The sun at the Julian date `jd` (UT, continuous) seen from `latitude`/`longitude`.
/// An SPA failure is a parameter error naming `field`.
fn position_jd(jd: JulianDate, latitude: f64, longitude: f64, field: &str) -> Result<Sun> {
    let bad = |e: solar_positioning::Error| Error::param(field, format!("SPA: {e}"));
    let refraction = RefractionCorrection::new(1013.25, 12.0).map_err(bad)?;
    let pos = SolarPositions::new()
        .for_time_from_julian(jd)
        .and_then(|p| p.at(Location { latitude, longitude }, 0.0, Some(refraction)))
        .map_err(bad)?;
    Ok(Sun { azimuth_north_cw: pos.azimuth(), elevation: pos.elevation_angle() })
}

/// The sun over the local solar days `from`..=`to` (`YYYY-MM-DD`) at `latitude`/`longitude`,
/// sampled every `step_minutes` at the middle of each step (midpoint rule): a day is the 24 h
/// from local mean solar midnight, UTC − longitude/15 h. Only the steps with the sun above 0°
/// (apparent) are returned; each stands for `step_minutes` of the day.
///
/// # Errors
/// [`Error::Param`] naming `date` for a date SPA cannot take.
pub fn day_steps(
    from: &str,
    to: &str,
    step_minutes: u32,
    latitude: f64,
    longitude: f64,
) -> Result<Vec<Sun>> {
    use crate::params::{days_from_civil, parse_date};
    let (y, m, d) = parse_date("date_from", from)?;
    let days = days_from_civil(parse_date("date_to", to)?) - days_from_civil((y, m, d)) + 1;
    let bad = |e: solar_positioning::Error| Error::param("date", format!("SPA: {e}"));
    let dt = delta_t::estimate_from_date(y, m).map_err(bad)?;
    let midnight = JulianDate::from_utc(y, m, d, 0, 0, 0.0, dt).map_err(bad)?.julian_date()
        - longitude / 360.0;
    let per_day = 1440 / step_minutes;
    let mut out = Vec::new();
    for day in 0..days {
        for k in 0..per_day {
            let minutes = (f64::from(k) + 0.5) * f64::from(step_minutes);
            let jd = JulianDate::new(midnight + day as f64 + minutes / 1440.0, dt).map_err(bad)?;
            let sun = position_jd(jd, latitude, longitude, "date")?;
            if sun.elevation > 0.0 {
                out.push(sun);
            }
        }
    }
    Ok(out)
}

/// The direct normal irradiance of a clear sky, W/m², for the sun at apparent `elevation_deg`
/// and air `pressure_pa`: Ineichen's simplified Solis model (Ineichen 2008), as pvlib's
/// `clearsky.simplified_solis` computes it with its defaults (aerosol optical depth at 700 nm
/// 0.1, precipitable water 1 cm, extraterrestrial irradiance 1364 W/m²).
pub fn clear_sky_dni(elevation_deg: f64, pressure_pa: f64) -> f64 {
    const AOD700: f64 = 0.1;
    const W: f64 = 1.0;
    const I0: f64 = 1364.0;
    let lp = (pressure_pa / 101_325.0).ln();
    let lw = W.ln();
    let i0p = I0
        * (0.12 * W.powf(0.56) * AOD700 * AOD700
            + 0.97 * W.powf(0.032) * AOD700
            + 1.08 * W.powf(0.0051)
            + 0.071 * lp);
    let tb1 = 1.82 + 0.056 * lw + 0.0071 * lw * lw;
    let tb0 = 0.33 + 0.045 * lw + 0.0096 * lw * lw;
    let tbp = 0.0089 * W + 0.13;
    let taub = tb1 * AOD700 + tb0 + tbp * lp;
    let b1 = 0.00925 * AOD700 * AOD700 + 0.0148 * AOD700 - 0.0172;
    let b0 = -0.7565 * AOD700 * AOD700 + 0.5057 * AOD700 + 0.4557;
    let b = b1 * lw + b0;
    let sin_e = elevation_deg.to_radians().sin().max(1e-30);
    i0p * (-taub / sin_e.powf(b)).exp()
}

/// Air pressure (Pa) at `altitude_m` above sea level in the standard atmosphere, as pvlib's
/// `atmosphere.alt2pres`.
pub fn pressure_at(altitude_m: f64) -> f64 {
    100.0 * ((44_331.514 - altitude_m) / 11_880.516).powf(1.0 / 0.190_263_2)
}

/// Which way a sun (or any asked azimuth) points: on the grid (`east_ccw`: φ of SPEC §2 in
/// degrees, the grid's x axis) or a true compass azimuth (`north_cw` and every SPA sun), which
/// the bake turns into φ per texel with the map's convergence
/// ([`crate::heightmap::north::Compass`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SunAzimuth {
    Grid(f64),
    True(f64),
}

impl SunAzimuth {
    /// The azimuth as given, degrees.
    pub fn degrees(&self) -> f64 {
        match *self {
            SunAzimuth::Grid(d) | SunAzimuth::True(d) => d,
        }
    }

    /// φ (radians) at window texel (`x`, `y`) of `compass`'s window.
    #[inline]
    pub fn phi(&self, compass: &crate::heightmap::north::Compass, x: usize, y: usize) -> f64 {
        match *self {
            SunAzimuth::Grid(d) => d.rem_euclid(360.0).to_radians(),
            SunAzimuth::True(d) => compass.phi(x, y, d),
        }
    }
}

/// A shadow's sun as asked (flags or a query), checked before the map is read: a fixed
/// azimuth and elevation, or a time whose place may still be the DEM's centre.
#[derive(Debug, Clone, PartialEq)]
pub enum SunQuery {
    Fixed(SunAzimuth, f64),
    Time { time: String, place: Option<(f64, f64)> },
}

impl SunQuery {
    /// Parses `sun_azimuth` + `sun_elevation` (azimuth counted as `from` says), or `sun_time`
    /// with `latitude` + `longitude` (both, or neither: then the DEM's centre).
    ///
    /// # Errors
    /// [`Error::Param`] naming the missing or invalid field.
    pub fn parse(
        azimuth: Option<&str>,
        elevation: Option<&str>,
        time: Option<&str>,
        latitude: Option<&str>,
        longitude: Option<&str>,
        from: crate::params::AzimuthFrom,
    ) -> Result<SunQuery> {
        use crate::params::{parse_f64, AzimuthFrom};
        match (azimuth, elevation, time) {
            (Some(a), Some(e), None) => {
                let az = parse_f64("sun_azimuth", a)?;
                let el = parse_f64("sun_elevation", e)?;
                if !(-90.0..=90.0).contains(&el) {
                    return Err(Error::param(
                        "sun_elevation",
                        "must be between -90 and 90 degrees",
                    ));
                }
                let az = match from {
                    AzimuthFrom::EastCcw => SunAzimuth::Grid(az),
                    AzimuthFrom::NorthCw => SunAzimuth::True(az),
                };
                Ok(SunQuery::Fixed(az, el))
            }
            (None, None, Some(t)) => {
                let place = match (latitude, longitude) {
                    (Some(a), Some(o)) => {
                        Some((parse_f64("latitude", a)?, parse_f64("longitude", o)?))
                    }
                    (None, None) => None,
                    (None, Some(_)) => {
                        return Err(Error::param("latitude", "give latitude with longitude"))
                    }
                    (Some(_), None) => {
                        return Err(Error::param("longitude", "give longitude with latitude"))
                    }
                };
                // The time is checked now, whatever the place.
                position(t, place.map_or(0.0, |p| p.0), place.map_or(0.0, |p| p.1))?;
                Ok(SunQuery::Time { time: t.to_owned(), place })
            }
            _ => Err(Error::param(
                "sun_azimuth",
                "give sun_azimuth and sun_elevation, or sun_time (with latitude and longitude, \
                 or a DEM whose centre places it)",
            )),
        }
    }

    /// The sun: its azimuth, apparent elevation, and the SPA position when one was computed,
    /// at the query's place or else `centre` (latitude, longitude of the DEM's centre).
    ///
    /// # Errors
    /// [`Error::Param`] naming `latitude` when a time has no place.
    pub fn resolve(&self, centre: Option<(f64, f64)>) -> Result<(SunAzimuth, f64, Option<Sun>)> {
        match self {
            SunQuery::Fixed(az, el) => Ok((*az, *el, None)),
            SunQuery::Time { time, place } => {
                let (lat, lon) = place.or(centre).ok_or_else(|| {
                    Error::param(
                        "latitude",
                        "sun_time needs latitude and longitude: this map has no projection \
                         that places its centre",
                    )
                })?;
                let sun = position(time, lat, lon)?;
                Ok((SunAzimuth::True(sun.azimuth_north_cw), sun.elevation, Some(sun)))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_rfc3339() {
        assert_eq!(parse_rfc3339("2026-06-21T12:00:00Z"), Some((2026, 6, 21, 12, 0, 0.0, 0)));
        assert_eq!(
            parse_rfc3339("2026-06-21T14:30:15.5+02:00"),
            Some((2026, 6, 21, 14, 30, 15.5, 120))
        );
        assert_eq!(parse_rfc3339("2026-06-21T08:00:00-05:30").map(|p| p.6), Some(-330));
        assert_eq!(parse_rfc3339("2026-13-01T00:00:00Z"), None);
        assert_eq!(parse_rfc3339("yesterday"), None);
    }

    #[test]
    fn offsets_name_the_same_instant() {
        let a = position("2026-06-21T12:00:00Z", 49.6, 6.1).unwrap();
        let b = position("2026-06-21T14:00:00+02:00", 49.6, 6.1).unwrap();
        assert!(
            (a.elevation - b.elevation).abs() < 1e-9
                && (a.azimuth_north_cw - b.azimuth_north_cw).abs() < 1e-9
        );
        // Near noon at 6° E in June, the sun stands high in the south.
        assert!(a.elevation > 60.0 && (150.0..210.0).contains(&a.azimuth_north_cw), "{a:?}");
    }
}
