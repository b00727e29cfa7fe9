//! Block compression (SPEC §8 `texture_precision=bc7|bc5`): the block-encoder crate behind one
//! function, [`compress`], which turns one RGBA8 image into BC7_UNORM or BC5_UNORM blocks.
//!
//! **Why image-rs's `dds` crate.** NOTES.md measured two encoders on this kind of machine (2
//! cores, one 2048² horizon layer): `intel_tex_2` (Intel's ISPC kernels, shipped prebuilt) BC7
//! `very_fast` 0.77 s at 43.9 dB, BC5 5 ms; `dds` 0.2 BC7 `Fast` 0.72 s at 43.7 dB, BC5 88 ms.
//! Same BC7 speed and quality; `intel_tex_2` links only with a build.rs that links `stdc++` and
//! ships opaque object files, `dds` is 100% safe Rust and builds wherever `cargo` does, so `dds`.
//! Its BC5 is slower, but small beside a bake. Measured again here, both layers of a 2048² bake
//! (`cargo test --locked --test encode textures::measure_2048 -- --ignored --nocapture`, test profile,
//! one run on a machine shared with three other builds, so times are high): bake 0.44 s; BC7
//! 3.9 s at 51.1 dB on rolling hills, 5.3 s at 23.9 dB on white noise; BC5 0.86 s at 57.8 dB /
//! 3.2 s at 31.0 dB; RGBA8 + zstd 3 0.39 s. BC7 spends its 128 bits on four independent
//! channels, which noise-like horizons punish; BC5 (two channels per block) keeps ~7 dB more.
//!
//! Blocks are encoded from the 8-bit layer values (SPEC §8), in bands of block rows on rayon
//! (each band one call of the crate, single-threaded inside); the progress's cancel flag is
//! checked before each band. A texture whose width or height is not a multiple of 4 has its
//! partial blocks padded by the crate (edge texels repeated), as every BC encoder does.

use crate::error::{Error, Result};
use crate::progress::Progress;
use rayon::prelude::*;

/// A block-compressed format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BlockFormat {
    /// BC7_UNORM: RGBA, 16 bytes per 4×4 block.
    Bc7,
    /// BC5_UNORM: the R and G channels of the input, 16 bytes per 4×4 block.
    Bc5,
}

/// Bytes of a `width × height` image in 4×4 blocks of 16 bytes.
pub fn compressed_len(width: usize, height: usize) -> usize {
    width.div_ceil(4) * height.div_ceil(4) * 16
}

/// Images of at most this many texels (256²) are BC7-encoded at `High` quality: a 2048² chain's
/// levels from 256² down add about 1/48 of level 0's texels, so ~10× the time per texel costs
/// ~20% of level 0's encode, and buys 5–10 dB where the mips' texels vary most.
const SMALL: usize = 256 * 256;

/// Block rows per rayon task: about 64 blocks' worth of texels at least, so the crate's own
/// per-call cost stays small, and enough bands that 2–16 threads all have work.
fn band_rows(width: usize, height: usize) -> usize {
    let block_rows = height.div_ceil(4);
    let by_work = (64usize).div_ceil(width.div_ceil(4)).max(1);
    by_work.max(block_rows / 64).max(1)
}

/// Compresses `rgba` (`width × height` RGBA8, rows from the top) into `format` blocks, rows of
/// blocks from the top.
///
/// # Errors
/// [`Error::Canceled`] when `progress` is canceled; [`Error::Internal`] when the sizes do not
/// match or the encoder fails.
pub fn compress(
    format: BlockFormat,
    width: usize,
    height: usize,
    rgba: &[u8],
    progress: &Progress,
) -> Result<Vec<u8>> {
    if width == 0 || height == 0 || rgba.len() != width * height * 4 {
        return Err(Error::Internal(format!(
            "bcn: {} bytes for a {width}×{height} RGBA image",
            rgba.len()
        )));
    }
    let fmt = match format {
        BlockFormat::Bc7 => dds::Format::BC7_UNORM,
        BlockFormat::Bc5 => dds::Format::BC5_UNORM,
    };
    let mut options = dds::EncodeOptions::default();
    options.parallel = false;
    options.quality = match format {
        // Small levels (mips) cost little at any quality, and their texels vary more per block.
        BlockFormat::Bc7 if width * height <= SMALL => dds::CompressionQuality::High,
        BlockFormat::Bc7 => dds::CompressionQuality::Fast,
        BlockFormat::Bc5 => dds::CompressionQuality::Normal,
    };
    let band = band_rows(width, height) * 4;
    let mut out = vec![0u8; compressed_len(width, height)];
    let band_bytes = compressed_len(width, band);
    out.par_chunks_mut(band_bytes).zip(rgba.par_chunks(band * width * 4)).try_for_each(
        |(dst, src)| -> Result<()> {
            if progress.is_canceled() {
                return Err(Error::Canceled);
            }
            let rows = src.len() / (width * 4);
            let view = dds::ImageView::new(
                src,
                dds::Size::new(width as u32, rows as u32),
                dds::ColorFormat::RGBA_U8,
            )
            .ok_or_else(|| Error::Internal("bcn: image view".into()))?;
            let mut w: &mut [u8] = dst;
            dds::encode(&mut w, view, fmt, None, &options)
                .map_err(|e| Error::Internal(format!("bcn: {e}")))?;
            if !w.is_empty() {
                return Err(Error::Internal("bcn: the encoder wrote a short band".into()));
            }
            Ok(())
        },
    )?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// BC5 of a flat block decodes to the flat value: the first 8 bytes hold red's two
    /// endpoints, the next 8 green's; a flat channel has both endpoints equal to it (or an
    /// index set that selects it).
    #[test]
    fn flat_image_compresses_to_its_value_and_bands_join_in_order() {
        for (w, h) in [(1, 1), (5, 3), (16, 40), (33, 9)] {
            let mut rgba = vec![0u8; w * h * 4];
            for (k, t) in rgba.chunks_exact_mut(4).enumerate() {
                let y = k / w;
                // Top half red 200, bottom half red 40; green 90 everywhere.
                t.copy_from_slice(&[if y < 4 { 200 } else { 40 }, 90, 7, 255]);
            }
            let p = Progress::new();
            let bc5 = compress(BlockFormat::Bc5, w, h, &rgba, &p).unwrap();
            assert_eq!(bc5.len(), compressed_len(w, h));
            for (b, block) in bc5.chunks_exact(16).enumerate() {
                let by = b / w.div_ceil(4);
                let red = if by == 0 { 200 } else { 40 };
                // Endpoint 0 of a flat BC4 block is the value (any encoder: the error is 0).
                assert!(block[0] == red || block[1] == red, "block {b} of {w}×{h}: {block:?}");
                assert!(block[8] == 90 || block[9] == 90, "block {b} of {w}×{h}: {block:?}");
            }
            let bc7 = compress(BlockFormat::Bc7, w, h, &rgba, &p).unwrap();
            assert_eq!(bc7.len(), compressed_len(w, h));
        }
        let p = Progress::new();
        p.cancel();
        assert!(matches!(compress(BlockFormat::Bc7, 4, 4, &[0; 64], &p), Err(Error::Canceled)));
        assert!(compress(BlockFormat::Bc7, 4, 4, &[0; 60], &Progress::new()).is_err());
    }
}
