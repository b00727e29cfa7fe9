//! Engine-ready textures (SPEC §8): the delivery options of `horizon.ktx2`/`horizon.dds` and the
//! cube map ([`TextureOptions`]), and the [`Texture`] both containers write: a pixel format, a
//! shape (array or cube) and every level of every image, already in the bytes the GPU reads.
//!
//! [`build`] is the one place that turns layer images into textures: mip chain
//! ([`super::mips`], or with `mip_filter=rebake` the levels baked again, given to
//! [`build_levels`]), block compression ([`super::bcn`], after filtering, from the 8-bit
//! values), the `bc5` split into four RG layers, and the `separate` layout (one texture per
//! layer). The containers ([`super::ktx2`], [`super::dds`]) only lay out what it gives them.

use super::bcn::{self, BlockFormat};
use super::mips::{self, MipFilter, Sample};
use super::{check_images, Shape, Texels};
use crate::error::{Error, Result};
use crate::progress::Progress;

/// The pixel format of a [`Texture`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelFormat {
    Rgba8Unorm,
    Rgba8Snorm,
    Rgba16Unorm,
    Rgba32Float,
    Bc7Unorm,
    Bc5Unorm,
}

impl PixelFormat {
    /// The format of uncompressed samples.
    pub fn of(t: &Texels<'_>) -> Self {
        match t {
            Texels::Unorm8(_) => PixelFormat::Rgba8Unorm,
            Texels::Snorm8(_) => PixelFormat::Rgba8Snorm,
            Texels::Unorm16(_) => PixelFormat::Rgba16Unorm,
            Texels::Float32(_) => PixelFormat::Rgba32Float,
        }
    }

    /// Whether the format is made of 4×4 blocks.
    pub fn is_block(self) -> bool {
        matches!(self, PixelFormat::Bc7Unorm | PixelFormat::Bc5Unorm)
    }

    /// Bytes of one texel (uncompressed) or one 4×4 block.
    pub fn block_bytes(self) -> usize {
        match self {
            PixelFormat::Rgba8Unorm | PixelFormat::Rgba8Snorm => 4,
            PixelFormat::Rgba16Unorm => 8,
            PixelFormat::Rgba32Float | PixelFormat::Bc7Unorm | PixelFormat::Bc5Unorm => 16,
        }
    }

    /// Bytes of one `width × height` image.
    pub fn image_bytes(self, width: usize, height: usize) -> usize {
        if self.is_block() {
            bcn::compressed_len(width, height)
        } else {
            width * height * self.block_bytes()
        }
    }
}

/// A texture ready for a container: `levels[level][image]`, images in layer (or face) order,
/// level 0 the largest; level `l` is `max(1, width >> l) × max(1, height >> l)`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Texture {
    pub format: PixelFormat,
    pub width: usize,
    pub height: usize,
    pub shape: Shape,
    pub levels: Vec<Vec<Vec<u8>>>,
}

impl Texture {
    /// A single-level texture of uncompressed images.
    ///
    /// # Errors
    /// [`Error::Internal`] when the images do not fit `width × height` RGBA or `shape`.
    pub fn single(
        width: usize,
        height: usize,
        shape: Shape,
        images: &[Texels<'_>],
    ) -> Result<Self> {
        check_images(width, height, shape, images)?;
        let level = images
            .iter()
            .map(|img| {
                let mut v = Vec::with_capacity(img.len() * img.sample_bytes());
                img.extend_le(&mut v);
                v
            })
            .collect();
        Ok(Texture {
            format: PixelFormat::of(&images[0]),
            width,
            height,
            shape,
            levels: vec![level],
        })
    }

    /// Number of images per level (array layers, or 6 faces).
    pub fn images(&self) -> usize {
        match self.shape {
            Shape::Array(n) => n as usize,
            Shape::Cube => 6,
        }
    }

    /// Width and height of level `l`.
    pub fn level_size(&self, l: usize) -> (usize, usize) {
        ((self.width >> l).max(1), (self.height >> l).max(1))
    }

    /// Checks that every level holds the images its size needs.
    ///
    /// # Errors
    /// [`Error::Internal`] naming the first level that does not.
    pub fn check(&self) -> Result<()> {
        if self.width == 0 || self.height == 0 || self.levels.is_empty() {
            return Err(Error::Internal("an empty texture".into()));
        }
        for (l, level) in self.levels.iter().enumerate() {
            let (w, h) = self.level_size(l);
            let want = self.format.image_bytes(w, h);
            if level.len() != self.images() || level.iter().any(|i| i.len() != want) {
                return Err(Error::Internal(format!("texture level {l} is not {w}×{h}")));
            }
        }
        Ok(())
    }
}

/// `texture_precision`: the sample type or block format of the KTX2/DDS horizon textures.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum TexturePrecision {
    /// R8G8B8A8_UNORM (the default, the precision of `png8`).
    #[default]
    Unorm8,
    /// R16G16B16A16_UNORM.
    Unorm16,
    /// R32G32B32A32_SFLOAT.
    Float32,
    /// BC7_UNORM blocks from the 8-bit layers, the 2-layer layout unchanged.
    Bc7,
    /// BC5_UNORM blocks, four layers of RG: channels (0,1), (2,3), (4,5), (6,7).
    Bc5,
}

impl TexturePrecision {
    /// Parses `unorm8`, `unorm16`, `float32`, `bc7` or `bc5`.
    ///
    /// # Errors
    /// [`Error::Param`] naming `texture_precision`.
    pub fn parse(value: &str) -> Result<Self> {
        match value.trim().to_ascii_lowercase().as_str() {
            "unorm8" => Ok(TexturePrecision::Unorm8),
            "unorm16" => Ok(TexturePrecision::Unorm16),
            "float32" => Ok(TexturePrecision::Float32),
            "bc7" => Ok(TexturePrecision::Bc7),
            "bc5" => Ok(TexturePrecision::Bc5),
            _ => Err(Error::param(
                "texture_precision",
                format!("`{value}` is not one of unorm8, unorm16, float32, bc7, bc5"),
            )),
        }
    }

    /// The spelling in parameters and flags.
    pub fn name(self) -> &'static str {
        match self {
            TexturePrecision::Unorm8 => "unorm8",
            TexturePrecision::Unorm16 => "unorm16",
            TexturePrecision::Float32 => "float32",
            TexturePrecision::Bc7 => "bc7",
            TexturePrecision::Bc5 => "bc5",
        }
    }

    /// The block format, for `bc7` and `bc5`.
    pub fn block(self) -> Option<BlockFormat> {
        match self {
            TexturePrecision::Bc7 => Some(BlockFormat::Bc7),
            TexturePrecision::Bc5 => Some(BlockFormat::Bc5),
            _ => None,
        }
    }
}

/// `texture_layout`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum TextureLayout {
    /// One array texture (2 layers, 4 for `bc5`).
    #[default]
    Array,
    /// One 2D texture per layer: `horizon_0.ktx2`, `horizon_1.ktx2`, …
    Separate,
}

/// `dds_header`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum DdsHeader {
    /// A DX10 header (DXGI format, array size); the pixel format has only DDPF_FOURCC.
    #[default]
    Dx10,
    /// No DX10 header: FourCC `ATI2` for BC5, masks for RGBA8 (one 2D texture or a cube).
    Legacy,
}

/// The delivery options of SPEC §8 for KTX2 and DDS files. They change no computed value, so
/// they are not bake parameters: the same bake serves every variant. Serialised (in
/// `bake.json`) as the parameters spell them, every key present.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TextureOptions {
    pub precision: TexturePrecision,
    /// `mips=full`: every level down to 1×1.
    pub mips: bool,
    pub mip_filter: MipFilter,
    /// `supercompression=zstd` at this level (KTX2 only); None is `none`.
    pub zstd_level: Option<i32>,
    pub layout: TextureLayout,
    pub dds_header: DdsHeader,
}

impl serde::Serialize for TextureOptions {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let mut m = s.serialize_map(Some(7))?;
        m.serialize_entry("texture_precision", self.precision.name())?;
        m.serialize_entry("mips", if self.mips { "full" } else { "none" })?;
        m.serialize_entry("mip_filter", self.mip_filter.name())?;
        m.serialize_entry(
            "supercompression",
            if self.zstd_level.is_some() { "zstd" } else { "none" },
        )?;
        m.serialize_entry("zstd_level", &self.zstd_level)?;
        m.serialize_entry(
            "texture_layout",
            if self.layout == TextureLayout::Separate { "separate" } else { "array" },
        )?;
        m.serialize_entry(
            "dds_header",
            if self.dds_header == DdsHeader::Legacy { "legacy" } else { "dx10" },
        )?;
        m.end()
    }
}

/// The default `zstd_level` (what KTX-Software's `ktx create --zstd` suggests as a start).
pub const DEFAULT_ZSTD_LEVEL: i32 = 3;

/// The option names, as query parameters (CLI flags are the same in kebab case).
pub const OPTION_KEYS: [&str; 7] = [
    "texture_precision",
    "mips",
    "mip_filter",
    "supercompression",
    "zstd_level",
    "texture_layout",
    "dds_header",
];

impl TextureOptions {
    /// The options from `(key, value)` pairs of [`OPTION_KEYS`] (a key given twice, or one not
    /// in the list, is an error), checked together.
    ///
    /// # Errors
    /// [`Error::Param`] naming the field.
    pub fn from_pairs<'a>(pairs: impl IntoIterator<Item = (&'a str, &'a str)>) -> Result<Self> {
        let mut o = TextureOptions::default();
        let mut seen: Vec<&str> = Vec::new();
        let (mut zstd, mut level) = (false, None);
        for (k, v) in pairs {
            if seen.contains(&k) {
                return Err(Error::param(k, "given more than once"));
            }
            seen.push(k);
            match k {
                "texture_precision" => o.precision = TexturePrecision::parse(v)?,
                "mips" => {
                    o.mips = match v.trim().to_ascii_lowercase().as_str() {
                        "none" => false,
                        "full" => true,
                        _ => {
                            return Err(Error::param(
                                "mips",
                                format!("`{v}` is not one of none, full"),
                            ))
                        }
                    }
                }
                "mip_filter" => o.mip_filter = MipFilter::parse(v)?,
                "supercompression" => {
                    zstd = match v.trim().to_ascii_lowercase().as_str() {
                        "none" => false,
                        "zstd" => true,
                        _ => {
                            return Err(Error::param(
                                "supercompression",
                                format!("`{v}` is not one of none, zstd"),
                            ))
                        }
                    }
                }
                "zstd_level" => {
                    level = Some(match v.trim().parse::<i32>() {
                        Ok(n) if (1..=19).contains(&n) => n,
                        _ => {
                            return Err(Error::param(
                                "zstd_level",
                                format!(
                                    "`{v}` is not a whole number from 1 to 19 (no --ultra levels)"
                                ),
                            ))
                        }
                    })
                }
                "texture_layout" => {
                    o.layout = match v.trim().to_ascii_lowercase().as_str() {
                        "array" => TextureLayout::Array,
                        "separate" => TextureLayout::Separate,
                        _ => {
                            return Err(Error::param(
                                "texture_layout",
                                format!("`{v}` is not one of array, separate"),
                            ))
                        }
                    }
                }
                "dds_header" => {
                    o.dds_header = match v.trim().to_ascii_lowercase().as_str() {
                        "dx10" => DdsHeader::Dx10,
                        "legacy" => DdsHeader::Legacy,
                        _ => {
                            return Err(Error::param(
                                "dds_header",
                                format!("`{v}` is not one of dx10, legacy"),
                            ))
                        }
                    }
                }
                other => return Err(Error::param(other, "is not a texture option")),
            }
        }
        if level.is_some() && !zstd {
            return Err(Error::param("zstd_level", "applies only with supercompression=zstd"));
        }
        if seen.contains(&"mip_filter") && !o.mips {
            return Err(Error::param("mip_filter", "applies only with mips=full"));
        }
        o.zstd_level = zstd.then_some(level.unwrap_or(DEFAULT_ZSTD_LEVEL));
        Ok(o)
    }

    /// The options that differ from the defaults, as `key=value` pairs in [`OPTION_KEYS`]
    /// order: the canonical spelling of a variant (empty for the defaults).
    pub fn pairs(&self) -> Vec<(&'static str, String)> {
        let d = TextureOptions::default();
        let mut out = Vec::new();
        if self.precision != d.precision {
            out.push(("texture_precision", self.precision.name().to_owned()));
        }
        if self.mips {
            out.push(("mips", "full".to_owned()));
            if self.mip_filter != d.mip_filter {
                out.push(("mip_filter", self.mip_filter.name().to_owned()));
            }
        }
        if let Some(l) = self.zstd_level {
            out.push(("supercompression", "zstd".to_owned()));
            if l != DEFAULT_ZSTD_LEVEL {
                out.push(("zstd_level", l.to_string()));
            }
        }
        if self.layout == TextureLayout::Separate {
            out.push(("texture_layout", "separate".to_owned()));
        }
        if self.dds_header == DdsHeader::Legacy {
            out.push(("dds_header", "legacy".to_owned()));
        }
        out
    }

    /// The options one container takes of these (KTX2 drops `dds_header`, DDS drops
    /// `supercompression`): what a file of that container was written with, so a submission
    /// asking both containers at once names each variant as its own download does.
    pub fn for_container(&self, ktx2: bool) -> Self {
        if ktx2 {
            TextureOptions { dds_header: DdsHeader::default(), ..*self }
        } else {
            TextureOptions { zstd_level: None, ..*self }
        }
    }

    /// Checks the options against the containers they will be written in: `zstd` is for KTX2,
    /// a legacy DDS header holds one 2D texture (or a cube) of BC5, RGBA8, RGBA16 or f32.
    ///
    /// # Errors
    /// [`Error::Param`] naming the option that cannot apply.
    pub fn check_for(&self, ktx2: bool, dds: bool, cube: bool) -> Result<()> {
        if self.zstd_level.is_some() && !ktx2 {
            return Err(Error::param("supercompression", "applies only to KTX2 files"));
        }
        if self.dds_header == DdsHeader::Legacy && !dds {
            return Err(Error::param("dds_header", "applies only to DDS files"));
        }
        if cube && !matches!(self.precision, TexturePrecision::Unorm8 | TexturePrecision::Bc7) {
            return Err(Error::param(
                "texture_precision",
                "the cube map is RGBA8 SNORM, or BC7 blocks of its UNORM faces with \
                 texture_precision=bc7; it takes mips, mip_filter, supercompression and \
                 dds_header",
            ));
        }
        if cube && self.layout != TextureLayout::Array {
            return Err(Error::param("texture_layout", "the cube map is always one cube texture"));
        }
        if cube && self.mip_filter == MipFilter::Rebake {
            return Err(Error::param(
                "mip_filter",
                "rebake bakes horizon levels again from the heights, which the cube map has \
                 none of; use box, min or max",
            ));
        }
        if dds && self.dds_header == DdsHeader::Legacy {
            if self.precision == TexturePrecision::Bc7 {
                return Err(Error::param(
                    "dds_header",
                    "BC7 has no legacy FourCC; use dds_header=dx10 or texture_precision=bc5",
                ));
            }
            if !cube && self.layout == TextureLayout::Array {
                return Err(Error::param(
                    "dds_header",
                    "a legacy DDS header holds no array; add texture_layout=separate",
                ));
            }
        }
        Ok(())
    }
}

/// Samples the mip chain can filter and the containers can store.
trait Stored: Sample + Default {
    fn texels(v: &[Self]) -> Texels<'_>;
    /// The samples of `t` when they are of this type.
    fn of<'a>(t: &Texels<'a>) -> Option<&'a [Self]>;
}
impl Stored for u8 {
    fn texels(v: &[u8]) -> Texels<'_> {
        Texels::Unorm8(v)
    }
    fn of<'a>(t: &Texels<'a>) -> Option<&'a [u8]> {
        match *t {
            Texels::Unorm8(v) => Some(v),
            _ => None,
        }
    }
}
impl Stored for i8 {
    fn texels(v: &[i8]) -> Texels<'_> {
        Texels::Snorm8(v)
    }
    fn of<'a>(t: &Texels<'a>) -> Option<&'a [i8]> {
        match *t {
            Texels::Snorm8(v) => Some(v),
            _ => None,
        }
    }
}
impl Stored for u16 {
    fn texels(v: &[u16]) -> Texels<'_> {
        Texels::Unorm16(v)
    }
    fn of<'a>(t: &Texels<'a>) -> Option<&'a [u16]> {
        match *t {
            Texels::Unorm16(v) => Some(v),
            _ => None,
        }
    }
}
impl Stored for f32 {
    fn texels(v: &[f32]) -> Texels<'_> {
        Texels::Float32(v)
    }
    fn of<'a>(t: &Texels<'a>) -> Option<&'a [f32]> {
        match *t {
            Texels::Float32(v) => Some(v),
            _ => None,
        }
    }
}

/// Every level of one image as container bytes: filtered in its own sample type (or the
/// levels `given`, with `rebake`), then block-compressed when `block` says so.
fn image_levels<T: Stored>(
    width: usize,
    height: usize,
    img: &[T],
    given: &[Texels<'_>],
    opts: &TextureOptions,
    block: Option<BlockFormat>,
    progress: &Progress,
) -> Result<Vec<Vec<u8>>> {
    let n = if opts.mips { mips::full_levels(width, height) } else { 1 };
    let below: Vec<Vec<T>> = if given.is_empty() {
        mips::chain(width, height, img, opts.mip_filter, n, &|| !progress.is_canceled())?
    } else {
        if given.len() != n - 1 {
            return Err(Error::Internal(format!(
                "{} rebaked levels for a chain of {n}",
                given.len()
            )));
        }
        given
            .iter()
            .map(|t| {
                T::of(t).map(<[T]>::to_vec).ok_or_else(|| {
                    Error::Internal("rebaked levels must share level 0's sample type".into())
                })
            })
            .collect::<Result<_>>()?
    };
    let mut out = Vec::with_capacity(n);
    let (mut w, mut h) = (width, height);
    for level in std::iter::once(img).chain(below.iter().map(Vec::as_slice)) {
        if progress.is_canceled() {
            return Err(Error::Canceled);
        }
        let t = T::texels(level);
        out.push(match (block, t) {
            (Some(b), Texels::Unorm8(px)) => bcn::compress(b, w, h, px, progress)?,
            (Some(_), _) => {
                return Err(Error::Internal("block formats are encoded from 8-bit layers".into()))
            }
            (None, t) => {
                let mut v = Vec::with_capacity(t.len() * t.sample_bytes());
                t.extend_le(&mut v);
                v
            }
        });
        (w, h) = (mips::next_size(w), mips::next_size(h));
    }
    Ok(out)
}

/// The RG pairs of `bc5`: channels (2k, 2k+1) of `rgba` in R and G of a new RGBA8 image
/// (B = 0, A = 255; BC5 keeps only R and G).
fn rg_pair(rgba: &[u8], k: usize) -> Vec<u8> {
    let mut out = vec![0u8; rgba.len()];
    for (o, i) in out.chunks_exact_mut(4).zip(rgba.chunks_exact(4)) {
        o.copy_from_slice(&[i[2 * k], i[2 * k + 1], 0, 255]);
    }
    out
}

/// Turns images (the horizon layers, or the six cube faces) into the textures `opts` asks for:
/// one array or cube texture, or one 2D texture per layer with `texture_layout=separate`.
/// `bc7`/`bc5` need `Unorm8` images; `bc5` turns 2 RGBA layers into 4 RG layers. Horizon
/// layers with `mips=full` and `mip_filter=rebake` need their levels baked again: use
/// [`build_levels`].
///
/// # Errors
/// [`Error::Canceled`] when `progress` is canceled (checked between levels and layers, and
/// between bands of blocks); [`Error::Internal`] for images that do not fit.
pub fn build(
    width: usize,
    height: usize,
    shape: Shape,
    images: &[Texels<'_>],
    opts: &TextureOptions,
    progress: &Progress,
) -> Result<Vec<Texture>> {
    build_levels(width, height, shape, &[images.to_vec()], opts, progress)
}

/// Whether `opts` make the levels of an array texture from a bake of each level's heights
/// rather than from the level above (`mips=full`, `mip_filter=rebake`).
pub fn rebakes(opts: &TextureOptions) -> bool {
    opts.mips && opts.mip_filter == MipFilter::Rebake
}

/// [`build`] with every level given: `levels[l][image]`, level `l` of
/// `max(1, width >> l) × max(1, height >> l)` texels. An array texture under [`rebakes`] needs
/// the whole chain (`mips::full_levels` levels, quantised as level 0); otherwise only
/// `levels[0]` is given and the filter makes the rest (the cube map, which holds no heights,
/// is box-filtered under `rebake`).
///
/// # Errors
/// As [`build`]; [`Error::Internal`] when the levels given do not make the chain.
pub fn build_levels(
    width: usize,
    height: usize,
    shape: Shape,
    levels: &[Vec<Texels<'_>>],
    opts: &TextureOptions,
    progress: &Progress,
) -> Result<Vec<Texture>> {
    let images = levels.first().ok_or_else(|| Error::Internal("no level 0".into()))?;
    check_images(width, height, shape, images)?;
    let want = if rebakes(opts) && matches!(shape, Shape::Array(_)) {
        mips::full_levels(width, height)
    } else {
        1
    };
    if levels.len() != want {
        return Err(Error::Internal(format!(
            "{} levels given; this texture takes {want} (mip_filter=rebake gives them all)",
            levels.len()
        )));
    }
    for (l, level) in levels.iter().enumerate().skip(1) {
        let (w, h) = ((width >> l).max(1), (height >> l).max(1));
        check_images(w, h, shape, level)?;
    }
    let block = opts.precision.block();
    // split[l][image] for bc5: each RGBA layer as two RG layers.
    let split: Vec<Vec<Vec<u8>>>;
    let levels: Vec<Vec<Texels<'_>>> = match (opts.precision, shape) {
        (TexturePrecision::Bc5, Shape::Array(_)) => {
            split = levels
                .iter()
                .map(|level| {
                    Ok(level
                        .iter()
                        .map(|t| match t {
                            Texels::Unorm8(px) => Ok([rg_pair(px, 0), rg_pair(px, 1)]),
                            _ => Err(Error::Internal("bc5 is encoded from 8-bit layers".into())),
                        })
                        .collect::<Result<Vec<_>>>()?
                        .into_iter()
                        .flatten()
                        .collect())
                })
                .collect::<Result<_>>()?;
            split.iter().map(|l| l.iter().map(|v| Texels::Unorm8(v)).collect()).collect()
        }
        _ => levels.to_vec(),
    };
    let images = &levels[0];
    let format = match opts.precision {
        TexturePrecision::Bc7 => PixelFormat::Bc7Unorm,
        TexturePrecision::Bc5 => PixelFormat::Bc5Unorm,
        _ => PixelFormat::of(&images[0]),
    };
    // per_image[i][level]
    let mut per_image = Vec::with_capacity(images.len());
    for (i, img) in images.iter().enumerate() {
        if progress.is_canceled() {
            return Err(Error::Canceled);
        }
        let given: Vec<Texels<'_>> = levels[1..].iter().map(|l| l[i]).collect();
        let g = given.as_slice();
        per_image.push(match *img {
            Texels::Unorm8(p) => image_levels(width, height, p, g, opts, block, progress)?,
            Texels::Snorm8(p) => image_levels(width, height, p, g, opts, block, progress)?,
            Texels::Unorm16(p) => image_levels(width, height, p, g, opts, block, progress)?,
            Texels::Float32(p) => image_levels(width, height, p, g, opts, block, progress)?,
        });
    }
    let texture = |shape: Shape, imgs: Vec<Vec<Vec<u8>>>| -> Result<Texture> {
        let n = imgs.first().map_or(0, Vec::len);
        let mut levels: Vec<Vec<Vec<u8>>> = (0..n).map(|_| Vec::new()).collect();
        for img in imgs {
            for (l, bytes) in img.into_iter().enumerate() {
                levels[l].push(bytes);
            }
        }
        let t = Texture { format, width, height, shape, levels };
        t.check()?;
        Ok(t)
    };
    match (shape, opts.layout) {
        (Shape::Array(_), TextureLayout::Separate) => {
            per_image.into_iter().map(|img| texture(Shape::Array(1), vec![img])).collect()
        }
        (Shape::Array(_), TextureLayout::Array) => {
            let n = per_image.len() as u32;
            Ok(vec![texture(Shape::Array(n), per_image)?])
        }
        (Shape::Cube, _) => Ok(vec![texture(Shape::Cube, per_image)?]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options_parse_check_and_spell_back() {
        let o = TextureOptions::from_pairs([
            ("texture_precision", "bc5"),
            ("mips", "full"),
            ("mip_filter", "min"),
            ("supercompression", "zstd"),
            ("texture_layout", "separate"),
        ])
        .unwrap();
        assert_eq!(o.zstd_level, Some(3));
        assert_eq!(o.precision, TexturePrecision::Bc5);
        let again = TextureOptions::from_pairs(
            o.pairs().iter().map(|(k, v)| (*k, v.as_str())).collect::<Vec<_>>(),
        )
        .unwrap();
        assert_eq!(again, o);
        assert!(TextureOptions::default().pairs().is_empty());
        for (pairs, field) in [
            (vec![("zstd_level", "3")], "zstd_level"),
            (vec![("supercompression", "zstd"), ("zstd_level", "23")], "zstd_level"),
            (vec![("mip_filter", "max")], "mip_filter"),
            (vec![("mip_filter", "rebake")], "mip_filter"),
            (vec![("mips", "some")], "mips"),
            (vec![("texture_precision", "bc1")], "texture_precision"),
            (vec![("mips", "full"), ("mips", "full")], "mips"),
            (vec![("dds_header", "dx9")], "dds_header"),
        ] {
            match TextureOptions::from_pairs(pairs.clone()) {
                Err(Error::Param { field: f, .. }) => assert_eq!(f, field, "{pairs:?}"),
                other => panic!("{pairs:?}: {other:?}"),
            }
        }
        let legacy = TextureOptions { dds_header: DdsHeader::Legacy, ..Default::default() };
        assert!(legacy.check_for(false, true, false).is_err(), "an array needs separate");
        assert!(legacy.check_for(false, true, true).is_ok(), "a cube is fine");
        let sep = TextureOptions { layout: TextureLayout::Separate, ..legacy };
        assert!(sep.check_for(false, true, false).is_ok());
        let bc7 = TextureOptions { precision: TexturePrecision::Bc7, ..sep };
        assert!(bc7.check_for(false, true, false).is_err());
        let z = TextureOptions { zstd_level: Some(3), ..Default::default() };
        assert!(z.check_for(false, true, false).is_err());
        assert!(z.check_for(true, true, false).is_ok());
    }

    #[test]
    fn rebake_boxes_the_cube_and_needs_every_level_of_an_array() {
        let n = 4;
        let faces: Vec<Vec<i8>> = (0..6)
            .map(|f| {
                (0..n * n * 4).map(|k| (((k * 7 + f * 13) % 200) as i32 - 100) as i8).collect()
            })
            .collect();
        let imgs: Vec<Texels<'_>> = faces.iter().map(|f| Texels::Snorm8(f)).collect();
        let p = Progress::new();
        let rebake =
            TextureOptions { mips: true, mip_filter: MipFilter::Rebake, ..Default::default() };
        let boxed = TextureOptions { mips: true, ..Default::default() };
        assert_eq!(
            build(n, n, Shape::Cube, &imgs, &rebake, &p).unwrap(),
            build(n, n, Shape::Cube, &imgs, &boxed, &p).unwrap()
        );
        let l: Vec<u8> = (0..n * n * 4).map(|k| k as u8).collect();
        let two = [Texels::Unorm8(&l), Texels::Unorm8(&l)];
        assert!(matches!(build(n, n, Shape::Array(2), &two, &rebake, &p), Err(Error::Internal(_))));
    }

    #[test]
    fn bc5_makes_four_rg_layers_and_separate_one_texture_each() {
        let (w, h) = (8, 4);
        let l0: Vec<u8> = (0..w * h * 4).map(|k| (k % 4 * 60) as u8).collect();
        let l1: Vec<u8> = (0..w * h * 4).map(|k| (k % 4 * 60 + 10) as u8).collect();
        let imgs = [Texels::Unorm8(&l0), Texels::Unorm8(&l1)];
        let p = Progress::new();
        let o =
            TextureOptions { precision: TexturePrecision::Bc5, mips: true, ..Default::default() };
        let t = build(w, h, Shape::Array(2), &imgs, &o, &p).unwrap();
        assert_eq!(t.len(), 1);
        assert_eq!(t[0].shape, Shape::Array(4));
        assert_eq!(t[0].levels.len(), 4);
        assert_eq!(t[0].levels[0][0].len(), 2 * 16);
        assert_eq!(t[0].levels[3][3].len(), 16);
        // A flat channel: block endpoints hold it. Layer 3 = channels (6, 7) = layer 1's B, A.
        assert!(t[0].levels[0][3][0] == 130 || t[0].levels[0][3][1] == 130);
        assert!(t[0].levels[0][3][8] == 190 || t[0].levels[0][3][9] == 190);
        let o = TextureOptions { layout: TextureLayout::Separate, ..Default::default() };
        let t = build(w, h, Shape::Array(2), &imgs, &o, &p).unwrap();
        assert_eq!(t.len(), 2);
        assert_eq!(t[1].levels, vec![vec![l1.clone()]]);
        p.cancel();
        assert!(matches!(build(w, h, Shape::Array(2), &imgs, &o, &p), Err(Error::Canceled)));
    }
}
