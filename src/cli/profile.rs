//! `horizon-bake profile INPUT --at X,Y` (SPEC §6): the exact horizon profile at one texel, as
//! CSV (`azimuth_deg,elevation_deg`) or JSON, with the bake flags (DEM defaults included).

use crate::cli::bake::ParamFlags;
use crate::error::{Error, Result};
use crate::heightmap::{self, Limits};
use std::io::Write;
use std::path::PathBuf;

/// Flags of `horizon-bake profile`.
#[derive(Debug, Clone, clap::Args)]
#[command(
    mut_arg("method", |a| a.help("Ignored: a profile is always cast by exact rays")),
    mut_arg("radius", |a| a.help("Reach of the rays in texels, `unlimited` (default) or `auto`")),
    mut_arg("bins", |a| a.help("Azimuths of the profile, 1..3600 (default 360)")),
)]
pub struct ProfileArgs {
    /// The height map (a GeoTIFF DEM gets the DEM defaults).
    pub input: PathBuf,
    /// Texel column and row, `X,Y`.
    #[arg(long, allow_hyphen_values = true, conflicts_with = "at_map")]
    pub at: Option<String>,
    /// Map coordinates `E,N` in the input's CRS (a GeoTIFF).
    #[arg(long, allow_hyphen_values = true)]
    pub at_map: Option<String>,
    /// Print JSON instead of CSV.
    #[arg(long)]
    pub json: bool,
    /// The bake parameters (method is always exact; `--bins` is the profile's azimuth count,
    /// default 360, any 1..3600; `--radius` defaults to unlimited).
    #[command(flatten)]
    pub params: Box<ParamFlags>,
}

fn pair(field: &str, v: &str) -> Result<(f64, f64)> {
    let mut it = v.split(',').map(|p| p.trim().parse::<f64>());
    match (it.next(), it.next(), it.next()) {
        (Some(Ok(a)), Some(Ok(b)), None) if a.is_finite() && b.is_finite() => Ok((a, b)),
        _ => Err(Error::param(field, format!("`{v}` is not two numbers `A,B`"))),
    }
}

/// Runs `horizon-bake profile`.
///
/// # Errors
/// Parameter, decode and I/O errors, each one line.
pub fn run(args: ProfileArgs) -> Result<()> {
    let mut flags = (*args.params).clone();
    let bins = match flags.bins.take() {
        Some(b) => crate::params::parse_u32("bins", &b)?,
        None => 360,
    };
    if !(1..=3600).contains(&bins) {
        return Err(Error::param("bins", "must be between 1 and 3600 for a profile"));
    }
    // A profile looks to the edge of the map unless told otherwise (as PVGIS's does).
    if flags.radius.is_none() && flags.max_distance.is_none() {
        flags.radius = Some("unlimited".into());
    }
    let mut params = flags.params()?;
    if params.method != crate::params::Method::Exact {
        if let Some(m) = flags.method.as_deref() {
            eprintln!("note: a profile casts exact rays; --method {m} is not used");
        }
        params.set("method", "exact")?;
    }
    let bytes = std::fs::read(&args.input)
        .map_err(|e| Error::InvalidInput(format!("cannot read {}: {e}", args.input.display())))?;
    let (map, _) = heightmap::decode_for(&bytes, &mut params, &Limits::default())?;
    crate::bake::check_method_fits(&params, map.width as u32, map.height as u32)?;
    drop(bytes);
    let (x, y) = match (&args.at, &args.at_map) {
        (Some(at), _) => pair("at", at)?,
        (None, Some(at)) => {
            let (e, n) = pair("at_map", at)?;
            let t = map.terrain.georef.as_ref().and_then(|g| g.transform()).ok_or_else(|| {
                Error::param("at_map", "the input has no georeferencing; use --at X,Y")
            })?;
            // Texel centres sit half a texel inside the corner the transform names.
            ((e - t[0]) / t[1] - 0.5, (n - t[3]) / t[5] - 0.5)
        }
        (None, None) => return Err(Error::param("at", "give --at X,Y or --at-map E,N")),
    };
    let (xr, yr) = (x.round(), y.round());
    if xr < 0.0 || yr < 0.0 || xr >= map.width as f64 || yr >= map.height as f64 {
        return Err(Error::param(
            "at",
            format!("({x}, {y}) is outside the {}×{} map", map.width, map.height),
        ));
    }
    let p = crate::bake::horizon_profile(&map, &params, xr as usize, yr as usize, bins as usize)?;
    let text = if args.json {
        let v = serde_json::json!({
            "x": xr, "y": yr,
            "azimuth_from": params.azimuth_from,
            "profile": p.iter().map(|(a, e)| serde_json::json!({"azimuth": a, "elevation": e}))
                .collect::<Vec<_>>(),
        });
        format!("{v}\n")
    } else {
        crate::terrain::profile::to_csv(&p)
    };
    let mut out = std::io::stdout().lock();
    out.write_all(text.as_bytes())?;
    Ok(out.flush()?)
}
