//! PNG layers are never larger than their raw samples (plus the framing), at any size, in any
//! band, 8- and 16-bit, through the row writer and a real streaming bake; a smooth layer still
//! compresses. A regression test from tests/edges.rs (issue 25's sharp edges).

use crate::support::*;

/// Bytes a PNG of `raw` sample bytes in `rows` rows may add: a filter byte per row, 5 bytes per
/// stored deflate block (at most 64 KiB each; counted per 16 KiB to be safe), 12 per IDAT chunk
/// (1 MiB each), and the signature, IHDR, IEND and zlib header and checksum.
fn framing(raw: usize, rows: usize) -> usize {
    rows + 5 * (raw + rows).div_ceil(16 * 1024) + 12 * (raw / (1 << 20) + 1) + 8 + 25 + 12 + 6
}

/// A PNG layer is never larger than its raw samples (plus the framing), at every size and in
/// every band: a noise-like 1024² layer streamed in bands, 8- and 16-bit; a smooth one still
/// compresses.
#[test]
fn png_layers_are_never_larger_than_raw_at_any_size() {
    use horizon_bake::encode::png::{PngColor, PngRowWriter};
    let n = 1024usize;
    let mut rng = Rng(25);
    let noise8: Vec<u8> = (0..n * n * 4).map(|_| (rng.next_u64() >> 56) as u8).collect();
    let noise16: Vec<u16> = (0..n * n * 4).map(|_| (rng.next_u64() >> 48) as u16).collect();
    let band = 37 * n * 4; // uneven bands, as the streaming bake writes them
    let mut w8 = PngRowWriter::<_, u8>::new(Vec::new(), n, n, PngColor::Rgba).unwrap();
    let mut sizes = Vec::new();
    for rows in noise8.chunks(band) {
        w8.write_rows(rows).unwrap();
    }
    let png8 = w8.finish().unwrap();
    sizes.push(("png8 noise", png8.len(), n * n * 4));
    let mut w16 = PngRowWriter::<_, u16>::new(Vec::new(), n, n, PngColor::Rgba).unwrap();
    for rows in noise16.chunks(band) {
        w16.write_rows(rows).unwrap();
    }
    let png16 = w16.finish().unwrap();
    sizes.push(("png16 noise", png16.len(), n * n * 8));
    for (what, len, raw) in &sizes {
        assert!(*len <= raw + framing(*raw, n), "{what}: {len} bytes for {raw} of samples");
    }
    // Same samples back (a reader we did not write).
    let img = image::load_from_memory(&png16).unwrap().to_rgba16();
    assert!(img.as_raw() == &noise16);
    let img = image::load_from_memory(&png8).unwrap().to_rgba8();
    assert!(img.as_raw() == &noise8);

    // Half noise, half flat, in one image: each band is judged on its own (the flat half
    // compresses to almost nothing, the noisy half is stored), so the total is about half.
    let mut mixed = noise8.clone();
    mixed[n * n * 2..].fill(7);
    let mut w = PngRowWriter::<_, u8>::new(Vec::new(), n, n, PngColor::Rgba).unwrap();
    for rows in mixed.chunks(band) {
        w.write_rows(rows).unwrap();
    }
    let half = w.finish().unwrap();
    let raw_half = n * n * 2;
    assert!(half.len() <= raw_half + framing(raw_half, n / 2) + 64 * 1024, "{}", half.len());

    // A real bake of a rough 1024² map through the streaming pipeline, both precisions.
    let png = noise_png8(n, n, 77);
    let params =
        horizon_bake::params::BakeParams::from_pairs([("height_scale", "200"), ("radius", "4")])
            .unwrap();
    let (map, _) =
        horizon_bake::heightmap::decode(&png, params.channel, &Default::default()).unwrap();
    let progress = horizon_bake::progress::Progress::new();
    let (p8, _) = horizon_bake::pipeline::stream_horizon_pngs::<u8, _>(
        map.clone(),
        &params,
        &progress,
        [Vec::new(), Vec::new()],
    )
    .unwrap();
    let (p16, _) = horizon_bake::pipeline::stream_horizon_pngs::<u16, _>(
        map,
        &params,
        &progress,
        [Vec::new(), Vec::new()],
    )
    .unwrap();
    for (k, (a, b)) in p8.iter().zip(&p16).enumerate() {
        let (r8, r16) = (n * n * 4, n * n * 8);
        assert!(a.len() <= r8 + framing(r8, n), "layer {k} png8: {} for {r8}", a.len());
        assert!(b.len() <= r16 + framing(r16, n), "layer {k} png16: {} for {r16}", b.len());
    }

    // A smooth layer still compresses well.
    let smooth: Vec<u8> = (0..n * n * 4).map(|i| ((i / 4 % n) / 8) as u8).collect();
    let mut w = PngRowWriter::<_, u8>::new(Vec::new(), n, n, PngColor::Rgba).unwrap();
    w.write_rows(&smooth).unwrap();
    let small = w.finish().unwrap();
    assert!(small.len() * 20 < smooth.len(), "smooth layer: {} bytes", small.len());
}
