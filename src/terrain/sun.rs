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
    let refraction = RefractionCorrection::new(1013.25, 12.0).map_err(bad)?;
    let pos = SolarPositions::new()
        .for_time_from_julian(jd)
        .and_then(|p| p.at(Location { latitude, longitude }, 0.0, Some(refraction)))
        .map_err(bad)?;
    Ok(Sun { azimuth_north_cw: pos.azimuth(), elevation: pos.elevation_angle() })
}

/// The sun a shadow is asked for, as text from flags or a query: `sun_azimuth` + `sun_elevation`
/// (azimuth counted as `from` says), or `sun_time` + `latitude` + `longitude` (SPA). Returns the
/// azimuth in the `from` convention, the elevation, and the SPA sun when one was computed.
///
/// # Errors
/// [`Error::Param`] naming the missing or invalid field.
pub fn resolve(
    azimuth: Option<&str>,
    elevation: Option<&str>,
    time: Option<&str>,
    latitude: Option<&str>,
    longitude: Option<&str>,
    from: crate::params::AzimuthFrom,
    y_axis: crate::params::YAxis,
) -> Result<(f64, f64, Option<Sun>)> {
    use crate::params::{parse_f64, AzimuthFrom};
    match (azimuth, elevation, time) {
        (Some(a), Some(e), None) => {
            let az = parse_f64("sun_azimuth", a)?;
            let el = parse_f64("sun_elevation", e)?;
            if !(-90.0..=90.0).contains(&el) {
                return Err(Error::param("sun_elevation", "must be between -90 and 90 degrees"));
            }
            Ok((az, el, None))
        }
        (None, None, Some(t)) => {
            let lat = parse_f64("latitude", latitude.unwrap_or_default())?;
            let lon = parse_f64("longitude", longitude.unwrap_or_default())?;
            let sun = position(t, lat, lon)?;
            let az = match from {
                AzimuthFrom::NorthCw => sun.azimuth_north_cw,
                AzimuthFrom::EastCcw => crate::terrain::profile::tangent_azimuth(
                    sun.azimuth_north_cw,
                    AzimuthFrom::NorthCw,
                    y_axis,
                )
                .to_degrees(),
            };
            Ok((az, sun.elevation, Some(sun)))
        }
        _ => Err(Error::param(
            "sun_azimuth",
            "give sun_azimuth and sun_elevation, or sun_time with latitude and longitude",
        )),
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
