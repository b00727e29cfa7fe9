//! `horizon-bake cubemap -o DIR [--size N] [--format …]` (SPEC §6): the channel-factor cube map
//! as `cube_0.png` … `cube_5.png` (faces +X, −X, +Y, −Y, +Z, −Z; UNORM8 RGBA),
//! `cubemap.ktx2` and `cubemap.dds` (SNORM8 RGBA, so a zero factor is exact; or BC7 blocks of the
//! UNORM faces with `--texture-precision bc7`). Written all or nothing, like `bake`.

use crate::encode::{CubeFormats, MAX_CUBE_SIZE};
use crate::error::{Error, Result};
use crate::pipeline::cube_files;
use std::path::PathBuf;

/// Flags of `horizon-bake cubemap`.
#[derive(Debug, Clone, clap::Args)]
pub struct CubemapArgs {
    /// Output directory (created if missing).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Face size in texels (1 ..= 2048).
    #[arg(long, default_value = "16", allow_hyphen_values = true)]
    pub size: String,
    /// Comma list of png8 (default), ktx2, dds.
    #[arg(long, default_value = "png8")]
    pub format: String,
    /// unorm8 (default: RGBA8 SNORM texels, a zero factor exact) or bc7 (BC7 blocks of the
    /// UNORM faces of cube_N.png, f = 2t − 1: for loaders that read no uncompressed cube map,
    /// such as three.js's KTX2Loader).
    #[arg(long)]
    pub texture_precision: Option<String>,
    /// The SPEC §8 options of cubemap.ktx2 / cubemap.dds: --mips, --mip-filter (box, min or
    /// max), --supercompression, --zstd-level, --dds-header (the cube map stays one cube
    /// texture).
    #[command(flatten)]
    pub texture: super::bake::TextureFlags,
}

fn parse_formats(list: &str) -> Result<CubeFormats> {
    let mut f = CubeFormats::default();
    for part in list.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        match part.to_ascii_lowercase().as_str() {
            "png8" => f.png8 = true,
            "ktx2" => f.ktx2 = true,
            "dds" => f.dds = true,
            _ => {
                return Err(Error::param(
                    "format",
                    format!("`{part}` is not one of png8, ktx2, dds (for the cube map)"),
                ))
            }
        }
    }
    if !(f.png8 || f.ktx2 || f.dds) {
        return Err(Error::param("format", "must name at least one of png8, ktx2, dds"));
    }
    Ok(f)
}

fn parse_size(value: &str) -> Result<usize> {
    let n: u32 = value.trim().parse().map_err(|_| {
        Error::param(
            "size",
            format!("`{value}` is not a whole number between 1 and {MAX_CUBE_SIZE}"),
        )
    })?;
    if n == 0 || n > MAX_CUBE_SIZE {
        return Err(Error::param(
            "size",
            format!("must be between 1 and {MAX_CUBE_SIZE}, got {n}"),
        ));
    }
    Ok(n as usize)
}

/// Runs `horizon-bake cubemap`.
///
/// # Errors
/// [`Error::Param`] naming `size` or `format`; [`Error::Io`] when DIR cannot be written (left
/// untouched).
pub fn run(args: CubemapArgs) -> Result<()> {
    let size = parse_size(&args.size)?;
    let mut formats = parse_formats(&args.format)?;
    formats.texture = args.texture.options(args.texture_precision.as_deref())?;
    if formats.ktx2 || formats.dds {
        formats.texture.check_for(formats.ktx2, formats.dds, true)?;
        if formats.dds && formats.texture.zstd_level.is_some() {
            // As the service's downloads: each container takes the options it has.
            eprintln!("note: --supercompression zstd applies to the KTX2 files; DDS has none");
        }
    } else if let Some(option) = args
        .texture_precision
        .as_ref()
        .map(|_| "texture_precision")
        .or_else(|| args.texture.first_given())
    {
        return Err(Error::param(option, "applies only with --format ktx2 or dds"));
    }
    let files = cube_files(size, formats)?;
    super::bake::write_dir_atomically(&args.out, &files)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn size_and_format_errors_name_the_field() {
        for (size, format, field) in [
            ("0", "png8", "size"),
            ("4097", "png8", "size"),
            ("x", "png8", "size"),
            ("16", "exr", "format"),
        ] {
            let r = parse_size(size).and_then(|_| parse_formats(format));
            match r {
                Err(Error::Param { field: f, .. }) => assert_eq!(f, field, "{size} {format}"),
                other => panic!("{size} {format}: {other:?}"),
            }
        }
        assert_eq!(parse_size(" 1 ").unwrap(), 1);
    }

    #[test]
    fn files_per_format() {
        let f =
            cube_files(1, CubeFormats { png8: true, ktx2: true, ..Default::default() }).unwrap();
        let names: Vec<&str> = f.iter().map(|f| f.name).collect();
        assert_eq!(
            names[..6],
            ["cube_0.png", "cube_1.png", "cube_2.png", "cube_3.png", "cube_4.png", "cube_5.png"]
        );
        assert_eq!(names[6..], ["cubemap.ktx2"]);
        // A 1×1 +Z face looks straight up: azimuth 0, all of channel 0 → (255, 128, 128, 128).
        let img = image::load_from_memory(&f[4].bytes).unwrap().to_rgba8();
        assert_eq!(img.as_raw(), &[255, 128, 128, 128]);
    }
}
