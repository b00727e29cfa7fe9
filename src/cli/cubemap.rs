//! `horizon-bake cubemap -o DIR [--size N] [--format …]` (SPEC §6): the channel-factor cube map
//! as `cube_0.png` … `cube_5.png` (faces +X, −X, +Y, −Y, +Z, −Z; UNORM8 RGBA),
//! `cubemap.ktx2` and `cubemap.dds` (SNORM8 RGBA, so a zero factor is exact). Written all or
//! nothing, like `bake`.

use crate::encode::{self, OutFile, Shape, Texels};
use crate::error::{Error, Result};
use crate::kernels::cubemap;
use std::path::PathBuf;

/// Largest face size accepted: the factors of a 2048² cube already take 400 MB as f32, far more
/// than a 2-texel-wide blend ever needs (the default is 16).
pub const MAX_CUBE_SIZE: u32 = 2048;

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
}

/// Which cube-map files to write.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CubeFormats {
    pub png8: bool,
    pub ktx2: bool,
    pub dds: bool,
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

/// The cube-map files for face size `size`: PNG faces, KTX2 and DDS as `formats` asks.
///
/// # Errors
/// An encoder failure.
pub fn cube_files(size: usize, formats: CubeFormats) -> Result<Vec<OutFile>> {
    const NAMES: [&str; 6] =
        ["cube_0.png", "cube_1.png", "cube_2.png", "cube_3.png", "cube_4.png", "cube_5.png"];
    let factors = cubemap::cube_factors_shared(size);
    let face_len = size * size * 4;
    let mut out = Vec::new();
    if formats.png8 {
        for (face, name) in NAMES.into_iter().enumerate() {
            let bytes: Vec<u8> = factors[face * face_len..(face + 1) * face_len]
                .iter()
                .map(|&f| cubemap::unorm8(f))
                .collect();
            out.push(OutFile {
                name,
                bytes: encode::png::encode8(size, size, encode::png::PngColor::Rgba, &bytes)?,
            });
        }
    }
    if formats.ktx2 || formats.dds {
        let snorm: Vec<i8> = factors.iter().map(|&f| cubemap::snorm8(f)).collect();
        let faces: Vec<Texels<'_>> = snorm.chunks_exact(face_len).map(Texels::Snorm8).collect();
        if formats.ktx2 {
            out.push(OutFile {
                name: "cubemap.ktx2",
                bytes: encode::ktx2::encode(size, size, Shape::Cube, &faces)?,
            });
        }
        if formats.dds {
            out.push(OutFile {
                name: "cubemap.dds",
                bytes: encode::dds::encode(size, size, Shape::Cube, &faces)?,
            });
        }
    }
    Ok(out)
}

/// Runs `horizon-bake cubemap`.
///
/// # Errors
/// [`Error::Param`] naming `size` or `format`; [`Error::Io`] when DIR cannot be written (left
/// untouched).
pub fn run(args: CubemapArgs) -> Result<()> {
    let size = parse_size(&args.size)?;
    let formats = parse_formats(&args.format)?;
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
        let f = cube_files(1, CubeFormats { png8: true, ktx2: true, dds: false }).unwrap();
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
