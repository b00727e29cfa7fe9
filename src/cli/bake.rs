//! `horizon-bake bake INPUT -o DIR` (SPEC §6).
//!
//! Every bake parameter of SPEC §5 is a `--kebab-case` flag taken as text and passed through
//! [`BakeParams::set`], so a bad value fails with the same message (naming the field) as it does
//! over HTTP. The files come from [`crate::pipeline::produce`] (the service's worker runs the same
//! pipeline), written into a temporary
//! directory beside DIR (same file system) and only renamed into DIR once all of them were
//! written: a failed bake leaves DIR exactly as it was. A progress bar is drawn on stderr only
//! when stderr is a terminal.
//!
//! When the only horizon files asked for are PNGs, the bake is streamed
//! ([`crate::pipeline::stream_horizon_pngs`]):
//! bands of quantised rows go straight into row-streaming PNG writers on the staged files, so an
//! 8192² png16 bake never holds a whole layer or a whole encoded PNG (peak RSS ≈ the decoded
//! input; see benches/kernels.rs). Kernel and encoding then overlap, so `timings_ms.bake` covers
//! both and `encode` only what is left (Fourier outputs). EXR, KTX2 and DDS need whole layers
//! and take the whole-layer path.

use crate::bake::ResolvedRadius;
use crate::encode::{Formats, OutFile, TextureOptions, TexturePrecision};
use crate::error::{Error, Result};
use crate::heightmap::{self, InputInfo, Limits};
use crate::params::BakeParams;
use crate::pipeline;
use crate::progress::{Progress, Stage};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Flags of `horizon-bake bake`. Parameter values are strings on purpose: they are validated by
/// [`BakeParams::set`], not by clap, so messages are the same everywhere.
#[derive(Debug, Clone, clap::Args)]
pub struct BakeArgs {
    /// The height map: PNG (8/16-bit gray, gray+alpha, RGB, RGBA), TIFF (8/16-bit unsigned,
    /// 8/16/32-bit signed, 32/64-bit float; a GeoTIFF DEM gets the DEM defaults) or OpenEXR.
    pub input: PathBuf,
    /// Output directory (created if missing; files in it with the same names are replaced).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Comma list of png8 (default), png16, exr, ktx2, dds (the horizon layers and the surface
    /// maps normal, ao, bent_normal alike), geotiff (the terrain products of --outputs
    /// angles,svf).
    #[arg(long, default_value = "png8")]
    pub format: String,
    /// Sample type of horizon.ktx2 / horizon.dds: unorm8 (default), unorm16, float32, or the
    /// block formats bc7 (2 RGBA layers) and bc5 (4 RG layers), encoded from the 8-bit layers.
    #[arg(long, default_value = "unorm8")]
    pub texture_precision: String,
    /// The KTX2/DDS delivery options of SPEC §8 (mips, supercompression, layout, DDS header).
    #[command(flatten)]
    pub texture: LayerTextureFlags,
    /// Sample type of horizon_0.exr / horizon_1.exr: float (default, bit-exact) or half (half
    /// the size). Both uncompressed: no EXR compression pays for itself on horizon layers.
    #[arg(long, default_value = "float")]
    pub exr_precision: String,
    /// The bake parameters (SPEC §5). Boxed: thirteen strings would make this the one huge
    /// variant of the subcommand enum.
    #[command(flatten)]
    pub params: Box<ParamFlags>,
    /// Largest accepted width or height of the input, in texels.
    #[arg(long, default_value_t = Limits::default().max_dim)]
    pub max_dim: u32,
    /// Largest accepted width × height of the input.
    #[arg(long, default_value_t = Limits::default().max_texels)]
    pub max_texels: u64,
}

/// The SPEC §8 options of the KTX2 and DDS files, as text (checked by
/// [`TextureOptions::from_pairs`], as over HTTP). Shared by `bake` and `cubemap`.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct TextureFlags {
    /// none (default) or full: every mip level down to 1×1.
    #[arg(long)]
    pub mips: Option<String>,
    /// How a level is made (with --mips full): box (default), min or max of the level above, or
    /// rebake (baked again from the box-filtered heights at the halved radius; horizon layers
    /// only).
    #[arg(long)]
    pub mip_filter: Option<String>,
    /// KTX2 supercompression: none (default) or zstd (each level on its own).
    #[arg(long)]
    pub supercompression: Option<String>,
    /// Zstandard level, 1..=19 (default 3; with --supercompression zstd).
    #[arg(long, allow_hyphen_values = true)]
    pub zstd_level: Option<String>,
    /// dx10 (default) or legacy (FourCC ATI2 / RGBA masks, no DX10 header; one 2D texture).
    #[arg(long)]
    pub dds_header: Option<String>,
}

/// [`TextureFlags`] and the layout of the horizon layers' files, which only `bake` has (the
/// cube map is always one cube texture).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct LayerTextureFlags {
    #[command(flatten)]
    pub common: TextureFlags,
    /// array (default: one array texture) or separate (horizon_0.ktx2, horizon_1.ktx2, …).
    #[arg(long)]
    pub texture_layout: Option<String>,
}

impl TextureFlags {
    fn pairs(&self) -> [(&'static str, Option<&str>); 5] {
        [
            ("mips", self.mips.as_deref()),
            ("mip_filter", self.mip_filter.as_deref()),
            ("supercompression", self.supercompression.as_deref()),
            ("zstd_level", self.zstd_level.as_deref()),
            ("dds_header", self.dds_header.as_deref()),
        ]
    }

    /// The options these flags (and `precision`, when given) set.
    ///
    /// # Errors
    /// [`Error::Param`] naming the first invalid option.
    pub fn options(&self, precision: Option<&str>) -> Result<TextureOptions> {
        options_of(std::iter::once(("texture_precision", precision)).chain(self.pairs()))
    }

    /// The first option given, if any (for "applies only to KTX2/DDS" errors).
    pub fn first_given(&self) -> Option<&'static str> {
        self.pairs().into_iter().find_map(|(k, v)| v.is_some().then_some(k))
    }
}

impl LayerTextureFlags {
    /// The options these flags (and `precision`, when given) set.
    ///
    /// # Errors
    /// [`Error::Param`] naming the first invalid option.
    pub fn options(&self, precision: Option<&str>) -> Result<TextureOptions> {
        options_of(std::iter::once(("texture_precision", precision)).chain(self.pairs()))
    }

    /// The first option given, if any (for "applies only to KTX2/DDS" errors).
    pub fn first_given(&self) -> Option<&'static str> {
        self.pairs().into_iter().find_map(|(k, v)| v.is_some().then_some(k))
    }

    /// The common options with the layout in its place (before the DDS header, as SPEC §8
    /// lists them, so the first invalid one named is the same as over HTTP).
    fn pairs(&self) -> [(&'static str, Option<&str>); 6] {
        let [mips, filter, sc, level, dds] = self.common.pairs();
        [mips, filter, sc, level, ("texture_layout", self.texture_layout.as_deref()), dds]
    }
}

fn options_of<'a>(
    pairs: impl IntoIterator<Item = (&'static str, Option<&'a str>)>,
) -> Result<TextureOptions> {
    TextureOptions::from_pairs(pairs.into_iter().filter_map(|(k, v)| v.map(|v| (k, v))))
}

/// Every SPEC §5 parameter as a `--kebab-case` flag, as text.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ParamFlags {
    /// Height in texels of a normalised height of 1 (default 8).
    #[arg(long, allow_hyphen_values = true)]
    pub height_scale: Option<String>,
    /// Channel of an RGB(A) input: r, g, b, a or luma (default).
    #[arg(long)]
    pub channel: Option<String>,
    /// wrap (default: the map tiles) or none.
    #[arg(long)]
    pub edge: Option<String>,
    /// up (default, OpenGL) or down (DirectX).
    #[arg(long)]
    pub y_axis: Option<String>,
    /// lengyel, exact, march or sweep (default: lengyel for a plain image; for a GeoTIFF DEM
    /// sweep, or exact where sweep cannot run).
    #[arg(long)]
    pub method: Option<String>,
    /// Search radius in texels, `unlimited` or `auto` (default 16; unlimited for a GeoTIFF DEM
    /// without --method).
    #[arg(long, allow_hyphen_values = true)]
    pub radius: Option<String>,
    /// Azimuth bins (default 32): a multiple of 16 up to 256; any 1..720 for --outputs
    /// angles,svf alone with method exact, march or sweep.
    #[arg(long, allow_hyphen_values = true)]
    pub bins: Option<String>,
    /// average (default) or point (method=exact).
    #[arg(long)]
    pub reduce: Option<String>,
    /// Lowest light elevation in degrees; drives radius=auto (default 5).
    #[arg(long, allow_hyphen_values = true)]
    pub min_elevation_deg: Option<String>,
    /// linear (default) or sqrt.
    #[arg(long)]
    pub encoding: Option<String>,
    /// Comma list of horizon (default), fourier, angles, svf, horizon_distance, openness,
    /// sun_hours, insolation (GeoTIFF terrain products), normal, ao, bent_normal (surface maps:
    /// normal.png, ao.png, bent_normal.png).
    #[arg(long)]
    pub outputs: Option<String>,
    /// 3, 5 (default), 7 or 9.
    #[arg(long, allow_hyphen_values = true)]
    pub fourier_terms: Option<String>,
    /// standard (default) or expanded.
    #[arg(long)]
    pub fourier_range: Option<String>,
    /// Nodata value (holes): a number, nan, none, or auto (default: the file's GDAL_NODATA).
    #[arg(long, allow_hyphen_values = true)]
    pub nodata: Option<String>,
    /// Map units per texel (default: a GeoTIFF's pixel scale).
    #[arg(long, allow_hyphen_values = true)]
    pub cell_size: Option<String>,
    /// Radius in map units (needs a cell size); replaces --radius.
    #[arg(long, allow_hyphen_values = true)]
    pub max_distance: Option<String>,
    /// on or off (default: on for a GeoTIFF DEM with method exact, march or sweep).
    #[arg(long)]
    pub earth_curvature: Option<String>,
    /// Refraction coefficient of the curvature drop (default 0).
    #[arg(long, allow_hyphen_values = true)]
    pub refraction: Option<String>,
    /// Unit of angles.tif: degrees (default), radians or sin.
    #[arg(long)]
    pub angle_unit: Option<String>,
    /// Azimuths of angles.tif: east_ccw (default, the grid's x axis) or north_cw (compass, from
    /// true north where the DEM's projection gives it).
    #[arg(long)]
    pub azimuth_from: Option<String>,
    /// Sky-view factor: radiative (default, mean cos² α), visual (1 − mean sin α) or tilted
    /// (the tilted surface's own, Dozier & Frew for a slope).
    #[arg(long)]
    pub svf_model: Option<String>,
    /// The band of a multi-band TIFF the heights are in, 1..4 (a DEM with several bands needs
    /// it; default auto: --channel decides).
    #[arg(long)]
    pub band: Option<String>,
    /// Where the y of normal.png and bent_normal.png points in the image, whatever --y-axis:
    /// opengl (default, Y+, up: Godot, Blender, Unity) or directx (Y−, down: Unreal).
    #[arg(long)]
    pub normal_convention: Option<String>,
    /// What bent_normal.png holds: rgb (default), rg (x, y; blue 0) or rgb_ao (AO in alpha).
    #[arg(long)]
    pub bent_normal_encoding: Option<String>,
    /// The local solar day (YYYY-MM-DD) of --outputs sun_hours,insolation (sets --date-from and
    /// --date-to).
    #[arg(long, conflicts_with_all = ["date_from", "date_to"])]
    pub date: Option<String>,
    /// The first day (YYYY-MM-DD) of sun_hours/insolation over a range.
    #[arg(long, requires = "date_to")]
    pub date_from: Option<String>,
    /// The last day (YYYY-MM-DD, inclusive; at most 366 days after --date-from).
    #[arg(long, requires = "date_from")]
    pub date_to: Option<String>,
    /// Minutes between sun positions of sun_hours/insolation (default 10; divides 1440).
    #[arg(long)]
    pub time_step_minutes: Option<String>,
    /// Latitude of the sun's place in degrees (default: the DEM's centre).
    #[arg(long, allow_hyphen_values = true, requires = "longitude")]
    pub latitude: Option<String>,
    /// Longitude of the sun's place in degrees, east positive (default: the DEM's centre).
    #[arg(long, allow_hyphen_values = true, requires = "latitude")]
    pub longitude: Option<String>,
}

impl ParamFlags {
    /// The bake parameters these flags set (defaults elsewhere). Shared by `bake` and
    /// `preview`, so a flag means the same in both.
    ///
    /// # Errors
    /// [`Error::Param`] naming the first invalid field.
    pub fn params(&self) -> Result<BakeParams> {
        let pairs = [
            ("height_scale", &self.height_scale),
            ("channel", &self.channel),
            ("edge", &self.edge),
            ("y_axis", &self.y_axis),
            ("method", &self.method),
            ("radius", &self.radius),
            ("bins", &self.bins),
            ("reduce", &self.reduce),
            ("min_elevation_deg", &self.min_elevation_deg),
            ("encoding", &self.encoding),
            ("outputs", &self.outputs),
            ("fourier_terms", &self.fourier_terms),
            ("fourier_range", &self.fourier_range),
            ("nodata", &self.nodata),
            ("cell_size", &self.cell_size),
            ("max_distance", &self.max_distance),
            ("earth_curvature", &self.earth_curvature),
            ("refraction", &self.refraction),
            ("angle_unit", &self.angle_unit),
            ("azimuth_from", &self.azimuth_from),
            ("svf_model", &self.svf_model),
            ("band", &self.band),
            ("normal_convention", &self.normal_convention),
            ("bent_normal_encoding", &self.bent_normal_encoding),
            ("date", &self.date),
            ("date_from", &self.date_from),
            ("date_to", &self.date_to),
            ("time_step_minutes", &self.time_step_minutes),
            ("latitude", &self.latitude),
            ("longitude", &self.longitude),
        ];
        let p = BakeParams::from_pairs_unchecked(
            pairs.iter().filter_map(|(k, v)| v.as_deref().map(|v| (*k, v))),
        )?;
        // The full check runs with the DEM defaults, once the input is read.
        p.check_before_input()?;
        Ok(p)
    }
}

impl BakeArgs {
    /// The bake parameters these flags set (defaults elsewhere).
    ///
    /// # Errors
    /// [`Error::Param`] naming the first invalid field.
    pub fn params(&self) -> Result<BakeParams> {
        self.params.params()
    }

    fn limits(&self) -> Limits {
        Limits { max_dim: self.max_dim, max_texels: self.max_texels, ..Limits::default() }
    }
}

/// The CLI's [`pipeline::Sink`]: files go into the staging directory, and appear in DIR only
/// when the whole bake has succeeded ([`Staging::commit`]).
impl pipeline::Sink for Staging {
    type Writer = std::fs::File;

    fn writer(&mut self, name: &'static str) -> Result<std::fs::File> {
        self.create(name)
    }

    fn finish(&mut self, files: [(&'static str, std::fs::File); 2]) -> Result<()> {
        for (name, file) in files {
            self.add(name, file)?;
        }
        Ok(())
    }

    fn put(&mut self, file: OutFile) -> Result<()> {
        self.write(std::slice::from_ref(&file))
    }

    fn finish_one(&mut self, name: &'static str, file: std::fs::File) -> Result<()> {
        self.add(name, file)
    }
}

/// Milliseconds of a duration, for `timings_ms`.
fn ms(d: Duration) -> f64 {
    (d.as_secs_f64() * 1e6).round() / 1e3
}

/// Runs `horizon-bake bake`.
///
/// # Errors
/// [`Error::Param`] for a bad flag, the decode errors of [`heightmap::decode`] for a bad input,
/// [`Error::Io`] when the output cannot be written; DIR is left untouched in every case.
pub fn run(args: BakeArgs) -> Result<()> {
    let total = Instant::now();
    let mut params = args.params()?;
    let precision = TexturePrecision::parse(&args.texture_precision)?;
    // `geotiff` names the terrain products' files (SPEC §6), the rest the horizon layers'.
    let (geotiff, layer_formats): (Vec<&str>, Vec<&str>) = args
        .format
        .split(',')
        .map(str::trim)
        .filter(|p| !p.is_empty())
        .partition(|p| p.eq_ignore_ascii_case("geotiff"));
    let geotiff = !geotiff.is_empty();
    if geotiff != params.outputs.terrain() {
        return Err(Error::param(
            "format",
            if geotiff {
                "geotiff holds the terrain products: add --outputs angles,svf (or one of them, \
                 or horizon_distance)"
            } else {
                "--outputs angles, svf and horizon_distance are written as GeoTIFF: add --format \
                 geotiff"
            },
        ));
    }
    let layer_list = if geotiff && layer_formats.is_empty() && !params.outputs.horizon {
        "png8".to_owned()
    } else {
        layer_formats.join(",")
    };
    if params.outputs.horizon && layer_formats.is_empty() && geotiff {
        return Err(Error::param(
            "format",
            "--outputs includes horizon but --format names no horizon-layer format \
             (png8, png16, exr, ktx2, dds); add one, or drop horizon from --outputs",
        ));
    }
    let mut formats = Formats::parse(&layer_list, precision)?;
    formats.texture = args.texture.options(Some(&args.texture_precision))?;
    if formats.ktx2 || formats.dds {
        formats.texture.check_for(formats.ktx2, formats.dds, false)?;
        if formats.dds && formats.texture.zstd_level.is_some() {
            // As the service's downloads: each container takes the options it has.
            eprintln!("note: --supercompression zstd applies to the KTX2 files; DDS has none");
        }
    } else if let Some(option) = args.texture.first_given() {
        return Err(Error::param(option, "applies only with --format ktx2 or dds"));
    }
    formats.exr_precision =
        crate::encode::exr::ExrPrecision::parse("exr_precision", &args.exr_precision)?;
    // Without the horizon output or a surface map there is nothing to write as png16, EXR,
    // KTX2 or DDS; writing none while bake.json lists them would be a lie, so the combination
    // is refused. (png8, the default, stays accepted: the Fourier files are 8-bit PNGs.)
    let takes_formats = params.outputs.horizon || params.outputs.surface();
    if !takes_formats && (formats.png16 || formats.exr || formats.ktx2 || formats.dds) {
        return Err(Error::param(
            "format",
            format!(
                "`{}` names formats of the horizon layers and surface maps, but --outputs has \
                 neither; add one (--outputs horizon,fourier or normal, ao, bent_normal) or drop \
                 --format",
                args.format
            ),
        ));
    }
    check_out_dir(&args.out)?;
    let progress = Progress::new();

    let t = Instant::now();
    progress.start(Stage::Decode, 1);
    let bytes = std::fs::read(&args.input)
        .map_err(|e| Error::InvalidInput(format!("cannot read {}: {e}", args.input.display())))?;
    let (map, info) = heightmap::decode_for(&bytes, &mut params, &args.limits())?;
    let mut warnings = map.dem_warnings();
    // A DEM whose projection cannot be read is baked on grid north (SPEC §3.7): said where it
    // matters, compass bands and the sun.
    let compass_used = params.outputs.sun()
        || (params.outputs.terrain() && params.azimuth_from == crate::params::AzimuthFrom::NorthCw);
    if let Some(why) = crate::bake::compass_of(&map, &params).1.reason.filter(|_| compass_used) {
        warnings.push(format!("azimuths are taken from grid north: {why}"));
    }
    for w in &warnings {
        eprintln!("warning: {w}");
    }
    crate::bake::fit_method(&mut params, map.width as u32, map.height as u32, false)?;
    drop(bytes);
    let georeferencing = map
        .terrain
        .georef
        .as_ref()
        .filter(|g| g.is_dem())
        .map(|g| heightmap::georef::GeorefReport { warnings, ..g.report(params.cell_size) });
    let decode_ms = ms(t.elapsed());

    // One pipeline with the service's worker (crate::pipeline): PNG-only horizon outputs
    // stream straight into the staged files, everything else bakes whole layers first.
    let mut staging = Staging::new(&args.out)?;
    let size = params.outputs.horizon.then_some((map.width, map.height));
    let label = format!("{}×{}", map.width, map.height);
    let produced = with_progress_bar(&progress, label, || {
        pipeline::produce(map, &params, &formats, &progress, &mut staging)
    })?;
    // Encoding includes writing the files (to the staging directory): both are the cost of
    // producing the outputs. `total` ends before bake.json itself and the final renames.
    let (bake_ms, encode_ms) = (produced.bake_ms, produced.encode_ms + produced.store_ms);
    let radius = Some(produced.radius);
    let names = produced.names;
    let products = produced.products;
    let report = BakeReport {
        params: &params,
        resolved_radius: radius.as_ref(),
        formats: &formats,
        input: &info,
        input_path: &args.input,
        files: names,
        timings: [decode_ms, bake_ms, encode_ms, ms(total.elapsed())],
        size,
        georeferencing,
        products,
    };
    staging.write(&[OutFile { name: "bake.json", bytes: report.to_json()? }])?;
    staging.commit()
}

/// Everything `bake.json` reports.
struct BakeReport<'a> {
    params: &'a BakeParams,
    resolved_radius: Option<&'a ResolvedRadius>,
    formats: &'a Formats,
    input: &'a InputInfo,
    input_path: &'a Path,
    files: Vec<&'static str>,
    /// decode, bake, encode, total (ms).
    timings: [f64; 4],
    /// Width and height of the horizon layers, when baked.
    size: Option<(usize, usize)>,
    /// The DEM's georeferencing (SPEC §3.7), for a GeoTIFF input.
    georeferencing: Option<crate::heightmap::georef::GeorefReport>,
    /// What each terrain product holds (`null` without them).
    products: serde_json::Value,
}

impl BakeReport<'_> {
    fn to_json(&self) -> Result<Vec<u8>> {
        let mut params = serde_json::to_value(self.params)
            .map_err(|e| Error::Internal(format!("bake.json: {e}")))?;
        if let (Some(obj), Some(r)) = (params.as_object_mut(), self.resolved_radius) {
            obj.insert("resolved_radius".into(), serde_json::json!(r));
        }
        let mut input = serde_json::to_value(self.input)
            .map_err(|e| Error::Internal(format!("bake.json: {e}")))?;
        if let Some(obj) = input.as_object_mut() {
            obj.insert("path".into(), self.input_path.display().to_string().into());
        }
        let [decode, bake, encode, total] = self.timings;
        // What was written: without `horizon` in --outputs no layer format was (the png8 of the
        // Formats value is only its default), and `geotiff` is the terrain products' format.
        let mut formats = serde_json::to_value(self.formats)
            .map_err(|e| Error::Internal(format!("bake.json: {e}")))?;
        if let Some(obj) = formats.as_object_mut() {
            if !self.params.outputs.horizon {
                for layer_format in ["png8", "png16", "exr", "ktx2", "dds"] {
                    obj.insert(layer_format.into(), false.into());
                }
            }
            obj.insert("geotiff".into(), self.params.outputs.terrain().into());
        }
        let v = serde_json::json!({
            "params": params,
            "input": input,
            "output": {
                "formats": formats,
                "width": self.size.map(|s| s.0),
                "height": self.size.map(|s| s.1),
                "files": self.files,
            },
            "timings_ms": { "decode": decode, "bake": bake, "encode": encode, "total": total },
        });
        let mut v = v;
        if let Some(obj) = v.as_object_mut() {
            if let Some(g) = &self.georeferencing {
                obj.insert("georeferencing".into(), serde_json::json!(g));
            }
            if !self.products.is_null() {
                obj.insert("products".into(), self.products.clone());
            }
        }
        let mut out = serde_json::to_vec_pretty(&v)
            .map_err(|e| Error::Internal(format!("bake.json: {e}")))?;
        out.push(b'\n');
        Ok(out)
    }
}

/// Runs `work` while a thread polls `progress` into a progress bar on stderr — only when stderr is
/// a terminal, so piped output and logs stay clean.
fn with_progress_bar<T>(
    progress: &Progress,
    label: String,
    work: impl FnOnce() -> Result<T>,
) -> Result<T> {
    if !std::io::stderr().is_terminal() {
        return work();
    }
    let done = std::sync::atomic::AtomicBool::new(false);
    std::thread::scope(|s| {
        s.spawn(|| {
            let bar = indicatif::ProgressBar::new(1000);
            if let Ok(style) = indicatif::ProgressStyle::with_template(
                "bake {msg} [{elapsed_precise}] {wide_bar} {percent:>3}% eta {eta}",
            ) {
                bar.set_style(style);
            }
            bar.set_message(label);
            while !done.load(std::sync::atomic::Ordering::Relaxed) {
                if progress.stage() == Stage::Bake {
                    bar.set_position((progress.fraction() * 1000.0) as u64);
                }
                std::thread::sleep(Duration::from_millis(50));
            }
            bar.finish_and_clear();
        });
        let r = work();
        done.store(true, std::sync::atomic::Ordering::Relaxed);
        r
    })
}

/// Fails early when DIR exists but is not a directory.
fn check_out_dir(dir: &Path) -> Result<()> {
    if dir.exists() && !dir.is_dir() {
        return Err(Error::param(
            "out",
            format!("{} exists and is not a directory", dir.display()),
        ));
    }
    Ok(())
}

/// The nearest existing ancestor of `dir` (its parent, usually), where the temporary directory
/// goes so the final renames stay on one file system.
fn staging_parent(dir: &Path) -> PathBuf {
    let abs = if dir.is_absolute() {
        dir.to_path_buf()
    } else {
        std::env::current_dir().map(|c| c.join(dir)).unwrap_or_else(|_| dir.to_path_buf())
    };
    let mut p = abs.parent().map(Path::to_path_buf).unwrap_or_else(|| PathBuf::from("."));
    while !p.is_dir() {
        match p.parent() {
            Some(q) => p = q.to_path_buf(),
            None => return PathBuf::from("."),
        }
    }
    p
}

/// Files being written into a temporary directory beside DIR (same file system), moved into DIR
/// by [`Staging::commit`] only once every write succeeded. Dropping it without committing removes
/// the temporary directory and leaves DIR as it was.
pub struct Staging {
    dir: PathBuf,
    tmp: tempfile::TempDir,
    names: Vec<&'static str>,
}

impl Staging {
    /// Starts staging files for `dir`.
    ///
    /// # Errors
    /// [`Error::Param`] naming `out` when `dir` is a file; [`Error::Io`].
    pub fn new(dir: &Path) -> Result<Self> {
        check_out_dir(dir)?;
        let tmp = tempfile::Builder::new()
            .prefix(".horizon-bake-tmp-")
            .tempdir_in(staging_parent(dir))?;
        Ok(Staging { dir: dir.to_path_buf(), tmp, names: Vec::new() })
    }

    /// Writes `files` into the temporary directory and flushes them to disk.
    ///
    /// # Errors
    /// [`Error::Io`]; nothing in DIR has changed.
    pub fn write(&mut self, files: &[OutFile]) -> Result<()> {
        for f in files {
            let mut file = std::fs::File::create(self.tmp.path().join(f.name))?;
            std::io::Write::write_all(&mut file, &f.bytes)?;
            // Durable before it becomes visible under its final name.
            file.sync_all()?;
            self.names.push(f.name);
        }
        Ok(())
    }

    /// Creates `name` in the temporary directory for the caller to write (streamed outputs);
    /// it becomes part of the commit once handed back to [`Staging::add`].
    ///
    /// # Errors
    /// [`Error::Io`].
    pub fn create(&self, name: &str) -> Result<std::fs::File> {
        Ok(std::fs::File::create(self.tmp.path().join(name))?)
    }

    /// Flushes a file made by [`Staging::create`] to disk and stages it for the commit.
    ///
    /// # Errors
    /// [`Error::Io`].
    pub fn add(&mut self, name: &'static str, file: std::fs::File) -> Result<()> {
        file.sync_all()?;
        self.names.push(name);
        Ok(())
    }

    /// Creates DIR if missing and renames every staged file into it, then removes the
    /// temporary directory.
    ///
    /// # Errors
    /// [`Error::Io`].
    pub fn commit(self) -> Result<()> {
        std::fs::create_dir_all(&self.dir)?;
        for name in &self.names {
            std::fs::rename(self.tmp.path().join(name), self.dir.join(name))?;
        }
        self.tmp.close()?;
        Ok(())
    }
}

/// Writes `files` into `dir` all or nothing (see [`Staging`]).
///
/// # Errors
/// [`Error::Io`] (or [`Error::Param`] naming `out` when `dir` is a file). Before the renames
/// begin nothing in `dir` has changed.
pub fn write_dir_atomically(dir: &Path, files: &[OutFile]) -> Result<()> {
    let mut staging = Staging::new(dir)?;
    staging.write(files)?;
    staging.commit()
}
