//! `horizon-bake preview INPUT -o FILE.png` (SPEC §6): bakes what the shading needs and writes
//! the CPU preview (or a contact sheet) as PNG.
//!
//! Every flag is handed as text to [`BakeParams::set`] or [`PreviewParams::set`], so a value
//! means the same here as in a query string and fails with the same message. The PNG is written
//! to a temporary file beside the target and renamed into place, so nothing half-written is left.

use crate::error::{Error, Result};
use crate::heightmap::{self, Limits};
use crate::params::BakeParams;
use crate::preview::{self, PreviewParams};
use crate::progress::Progress;
use std::io::Write;
use std::path::PathBuf;

/// Flags of `horizon-bake preview`.
#[derive(Debug, clap::Args)]
pub struct PreviewArgs {
    /// The height map (PNG, TIFF or OpenEXR).
    pub input: PathBuf,
    /// The PNG to write (`-` writes it to standard output).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Every parameter flag (boxed: `Command` stays small, clippy's `large_enum_variant`).
    #[command(flatten)]
    pub flags: Box<PreviewFlags>,
}

/// The parameter flags of `horizon-bake preview`, each passed as text to the library's setters.
#[derive(Debug, clap::Args)]
pub struct PreviewFlags {
    // Preview parameters (SPEC §3.5).
    /// horizon | fourier | raytraced | none | difference. `difference` compares horizon with
    /// the raytraced ground truth: grey where they agree on lit vs shadowed, red where the
    /// horizon map shadows a lit texel, blue where it lights a shadowed one.
    #[arg(long)]
    pub shading: Option<String>,
    /// Light azimuth in degrees from +x toward +y.
    #[arg(long, allow_hyphen_values = true)]
    pub azimuth: Option<String>,
    /// Light elevation in degrees.
    #[arg(long, allow_hyphen_values = true)]
    pub elevation: Option<String>,
    /// Tangent-space light vector "x,y,z" (overrides azimuth/elevation).
    #[arg(long, allow_hyphen_values = true)]
    pub light: Option<String>,
    /// Hardness k of the soft shadow edge (default 8).
    #[arg(long)]
    pub hardness: Option<String>,
    /// View azimuth in degrees.
    #[arg(long, allow_hyphen_values = true)]
    pub view_azimuth: Option<String>,
    /// View elevation in degrees (90 = straight down, the default).
    #[arg(long)]
    pub view_elevation: Option<String>,
    /// Tangent-space view vector "x,y,z" (z > 0).
    #[arg(long, allow_hyphen_values = true)]
    pub view: Option<String>,
    /// none | offset | offset_limited | steep | interpolated | relief.
    #[arg(long)]
    pub parallax: Option<String>,
    /// Layers of the steep parallax family.
    #[arg(long)]
    pub parallax_steps: Option<String>,
    /// Bisections of relief mapping.
    #[arg(long)]
    pub parallax_search_steps: Option<String>,
    /// Parallax depth multiplier (1 = the map's true relief).
    #[arg(long)]
    pub parallax_strength: Option<String>,
    /// Horizon-occlusion fade of the specular reflection (0 = off).
    #[arg(long)]
    pub horizon_occlusion: Option<String>,
    /// Longer output side in pixels (default: one pixel per texel).
    #[arg(long)]
    pub size: Option<String>,
    /// Horizon layer precision the preview decodes: 8 or 16.
    #[arg(long)]
    pub precision: Option<String>,
    /// Cube-map face size the horizon shading samples (default 16).
    #[arg(long)]
    pub cube_size: Option<String>,
    /// Render a contact sheet of N light azimuths instead of one image.
    #[arg(long)]
    pub contact_sheet: Option<String>,
    /// Half the azimuth span of the contact sheet in degrees (default 60).
    #[arg(long)]
    pub sheet_spread: Option<String>,
    /// none (default) or baked: ambient and environment light times the bake's AO map
    /// (ao.png of the same method, radius and bins).
    #[arg(long)]
    pub ambient_occlusion: Option<String>,

    /// Bake parameters (SPEC §5), the same flags as `horizon-bake bake`.
    #[command(flatten)]
    pub bake: crate::cli::bake::ParamFlags,
}

impl PreviewFlags {
    /// The bake and preview parameters the flags name.
    ///
    /// # Errors
    /// [`Error::Param`] naming the first invalid flag (as the API spells it).
    pub fn params(&self) -> Result<(BakeParams, PreviewParams)> {
        let preview_flags = [
            ("shading", &self.shading),
            ("azimuth", &self.azimuth),
            ("elevation", &self.elevation),
            ("light", &self.light),
            ("hardness", &self.hardness),
            ("view_azimuth", &self.view_azimuth),
            ("view_elevation", &self.view_elevation),
            ("view", &self.view),
            ("parallax", &self.parallax),
            ("parallax_steps", &self.parallax_steps),
            ("parallax_search_steps", &self.parallax_search_steps),
            ("parallax_strength", &self.parallax_strength),
            ("horizon_occlusion", &self.horizon_occlusion),
            ("size", &self.size),
            ("precision", &self.precision),
            ("cube_size", &self.cube_size),
            ("contact_sheet", &self.contact_sheet),
            ("sheet_spread", &self.sheet_spread),
            ("ambient_occlusion", &self.ambient_occlusion),
        ];
        let bake = self.bake.params()?;
        let mut preview = PreviewParams::default();
        for (k, v) in preview_flags {
            if let Some(v) = v {
                preview.set(k, v)?;
            }
        }
        Ok((bake, preview))
    }
}

/// Runs `horizon-bake preview`.
///
/// # Errors
/// Decoding, parameter, limit and I/O errors, each with a one-line message.
pub fn run(args: PreviewArgs) -> Result<()> {
    let (mut bake, params) = args.flags.params()?;
    let to_stdout = args.output.as_os_str() == "-";
    // A missing directory is the caller's mistake (exit 2), found before any work is done.
    if !to_stdout {
        if let Some(dir) = args.output.parent().filter(|d| !d.as_os_str().is_empty()) {
            if !dir.is_dir() {
                return Err(Error::param(
                    "output",
                    format!("the directory {} does not exist", dir.display()),
                ));
            }
        }
    }
    let bytes = std::fs::read(&args.input).map_err(|e| {
        Error::Io(std::io::Error::new(e.kind(), format!("{}: {e}", args.input.display())))
    })?;
    let (map, _info) = heightmap::decode_for(&bytes, &mut bake, &Limits::default())?;
    crate::bake::fit_method(&mut bake, map.width as u32, map.height as u32, false)?;
    let image = preview::render_baking(&map, &bake, &params, &Progress::new())?;
    let png = image.to_png()?;
    if to_stdout {
        let mut out = std::io::stdout().lock();
        return match out.write_all(&png).and_then(|()| out.flush()) {
            // The reader stopped reading (`| head -c 8`, `| file -`): it has what it wanted.
            // Rust ignores SIGPIPE, so this is the error a C tool would have died of quietly.
            Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
            r => Ok(r?),
        };
    }
    write_atomically(&args.output, &png)
}

fn write_atomically(path: &std::path::Path, data: &[u8]) -> Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    // A temporary file is created 0600; the preview is an ordinary output, so it gets the mode
    // `bake`'s files get: 0666 less the umask (the kernel applies it to the mode asked for).
    let mut builder = tempfile::Builder::new();
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        builder.permissions(std::fs::Permissions::from_mode(0o666));
    }
    let mut tmp = builder
        .tempfile_in(&dir)
        .map_err(|e| Error::Io(std::io::Error::new(e.kind(), format!("{}: {e}", dir.display()))))?;
    tmp.write_all(data)?;
    tmp.persist(path).map_err(|e| {
        Error::Io(std::io::Error::new(e.error.kind(), format!("{}: {}", path.display(), e.error)))
    })?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct T {
        #[command(flatten)]
        a: PreviewArgs,
    }

    #[test]
    fn flags_reach_both_parameter_sets() {
        let t = T::try_parse_from([
            "x",
            "in.png",
            "-o",
            "out.png",
            "--azimuth",
            "-30",
            "--edge",
            "none",
            "--shading",
            "raytraced",
            "--contact-sheet",
            "9",
            "--y-axis",
            "down",
        ])
        .unwrap();
        let (b, p) = t.a.flags.params().unwrap();
        assert_eq!(b.edge, crate::params::Edge::None);
        assert_eq!(b.y_axis, crate::params::YAxis::Down);
        assert_eq!(p.azimuth, -30.0);
        assert_eq!(p.contact_sheet, 9);
        assert_eq!(p.shading, preview::Shading::Raytraced);
        let t = T::try_parse_from(["x", "in.png", "-o", "o.png", "--bins", "20"]).unwrap();
        match t.a.flags.params() {
            Err(Error::Param { field, .. }) => assert_eq!(field, "bins"),
            other => panic!("{other:?}"),
        }
    }
}
