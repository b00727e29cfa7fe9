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
    /// The time (RFC 3339, e.g. 2026-06-21T07:30:00Z) whose sun (NREL SPA) casts the shadow;
    /// with --latitude and --longitude, instead of --sun-azimuth/--sun-elevation.
    #[arg(long, conflicts_with_all = ["sun_azimuth", "sun_elevation"], requires_all = ["latitude", "longitude"])]
    pub sun_time: Option<String>,
    /// Latitude of the place in degrees (with --sun-time).
    #[arg(long, allow_hyphen_values = true)]
    pub latitude: Option<String>,
    /// Longitude of the place in degrees, east positive (with --sun-time).
    #[arg(long, allow_hyphen_values = true)]
    pub longitude: Option<String>,
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
    let (az, el, sun) = crate::terrain::sun::resolve(
        args.sun_azimuth.as_deref(),
        args.sun_elevation.as_deref(),
        args.sun_time.as_deref(),
        args.latitude.as_deref(),
        args.longitude.as_deref(),
        params.azimuth_from,
        params.y_axis,
    )?;
    if let (Some(sun), Some(t)) = (sun, &args.sun_time) {
        eprintln!(
            "sun at {t}: azimuth {:.4}° (from north, clockwise), elevation {:.4}°",
            sun.azimuth_north_cw, sun.elevation
        );
    }
    let bytes = std::fs::read(&args.input)
        .map_err(|e| Error::InvalidInput(format!("cannot read {}: {e}", args.input.display())))?;
    let (map, _) = heightmap::decode_for(&bytes, &mut params, &Limits::default())?;
    crate::bake::check_method_fits(&params, map.width as u32, map.height as u32)?;
    drop(bytes);
    let tif = crate::pipeline::shadow_tif(&map, &params, az, el, &Progress::new())?;
    // Written beside the target and renamed: a failure leaves no half-written file.
    let dir = args.out.parent().filter(|d| !d.as_os_str().is_empty()).map(PathBuf::from);
    let dir = dir.unwrap_or_else(|| PathBuf::from("."));
    let mut tmp = tempfile::NamedTempFile::new_in(&dir)
        .map_err(|e| Error::param("out", format!("cannot write in {}: {e}", dir.display())))?;
    std::io::Write::write_all(&mut tmp, &tif)?;
    tmp.persist(&args.out).map_err(|e| Error::Io(e.error))?;
    Ok(())
}
