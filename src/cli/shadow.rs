//! `horizon-bake shadow INPUT -o FILE.tif` (SPEC §6): the sun shadow of a height map or DEM as a
//! uint8 GeoTIFF (1 lit, 0 shadowed, 255 nodata), with the bake flags (DEM defaults included)
//! and the sun's azimuth (counted as `--azimuth-from` says) and elevation in degrees.

use crate::cli::bake::ParamFlags;
use crate::error::{Error, Result};
use crate::heightmap::{self, Limits};
use crate::progress::Progress;
use std::path::PathBuf;

/// Flags of `horizon-bake shadow`.
#[derive(Debug, Clone, clap::Args)]
#[command(
    mut_arg("method", |a| a.help("exact (default: one exact ray per texel at the sun's azimuth) \
        or lengyel (its baked layers decoded); march and sweep cast the same exact ray")),
    mut_arg("radius", |a| a.help("Reach of the ray in texels, `unlimited` (default) or `auto`")),
)]
pub struct ShadowArgs {
    /// The height map (a GeoTIFF DEM gets the DEM defaults).
    pub input: PathBuf,
    /// The GeoTIFF to write.
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Sun azimuth in degrees (east_ccw by default; compass with --azimuth-from north_cw).
    #[arg(long, allow_hyphen_values = true, requires = "sun_elevation")]
    pub sun_azimuth: Option<String>,
    /// Sun elevation in degrees (at or below 0 shadows everything).
    #[arg(long, allow_hyphen_values = true, requires = "sun_azimuth")]
    pub sun_elevation: Option<String>,
    /// The time (RFC 3339, e.g. 2026-06-21T07:30:00Z) whose sun (NREL SPA) casts the shadow,
    /// instead of --sun-azimuth/--sun-elevation; seen from --latitude/--longitude (degrees), or
    /// from a DEM's centre.
    #[arg(long, conflicts_with_all = ["sun_azimuth", "sun_elevation"])]
    pub sun_time: Option<String>,
    /// The bake parameters (`--radius` defaults to unlimited and the horizon is the exact ray's,
    /// unless `--method lengyel`, whose baked layers are decoded).
    #[command(flatten)]
    pub params: Box<ParamFlags>,
}

/// Runs `horizon-bake shadow`.
///
/// # Errors
/// Parameter, decode and I/O errors, each one line.
pub fn run(args: ShadowArgs) -> Result<()> {
    let mut flags = (*args.params).clone();
    // `--method lengyel` decodes its layers (SPEC §3.7) at its own radius; otherwise the shadow
    // is the exact ray's, to the edge unless a radius is given.
    let lengyel = flags.method.as_deref() == Some("lengyel");
    if !lengyel && flags.radius.is_none() && flags.max_distance.is_none() {
        flags.radius = Some("unlimited".into());
    }
    let mut params = flags.params()?;
    if !lengyel && params.method != crate::params::Method::Exact {
        if let Some(m) = flags.method.as_deref() {
            eprintln!("note: a shadow casts one exact ray per texel; --method {m} is not used");
        }
        params.set("method", "exact")?;
    }
    let query = crate::terrain::sun::SunQuery::parse(
        args.sun_azimuth.as_deref(),
        args.sun_elevation.as_deref(),
        args.sun_time.as_deref(),
        args.params.latitude.as_deref(),
        args.params.longitude.as_deref(),
        params.azimuth_from,
    )?;
    let bytes = std::fs::read(&args.input)
        .map_err(|e| Error::InvalidInput(format!("cannot read {}: {e}", args.input.display())))?;
    let (map, _) = heightmap::decode_for(&bytes, &mut params, &Limits::default())?;
    crate::bake::check_method_fits(&params, map.width as u32, map.height as u32)?;
    drop(bytes);
    let centre = crate::bake::centre_lat_lon(&map);
    if let (_, _, Some(sun)) = query.resolve(centre)? {
        let t = args.sun_time.as_deref().unwrap_or_default();
        let (lat, lon) = match (&args.params.latitude, centre) {
            (Some(_), _) | (None, None) => ("given".to_owned(), String::new()),
            (None, Some((a, o))) => (format!("{a:.5}"), format!("{o:.5}")),
        };
        let place = if lon.is_empty() {
            String::new()
        } else {
            format!(" at the DEM's centre {lat}° N {lon}° E")
        };
        eprintln!(
            "sun at {t}{place}: azimuth {:.4}° (from true north, clockwise), elevation {:.4}°",
            sun.azimuth_north_cw, sun.elevation
        );
    }
    let (_, north) = crate::bake::compass_of(&map, &params);
    if let Some(why) = &north.reason {
        eprintln!("warning: azimuths are taken from grid north: {why}");
    }
    let tif = crate::pipeline::shadow_tif(&map, &params, &query, &Progress::new())?;
    // Written beside the target and renamed: a failure leaves no half-written file.
    let dir = args.out.parent().filter(|d| !d.as_os_str().is_empty()).map(PathBuf::from);
    let dir = dir.unwrap_or_else(|| PathBuf::from("."));
    let mut tmp = tempfile::NamedTempFile::new_in(&dir)
        .map_err(|e| Error::param("out", format!("cannot write in {}: {e}", dir.display())))?;
    std::io::Write::write_all(&mut tmp, &tif)?;
    tmp.persist(&args.out).map_err(|e| Error::Io(e.error))?;
    Ok(())
}
