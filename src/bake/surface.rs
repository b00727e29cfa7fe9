//! The surface maps of a bake (SPEC §3.8): the normal, AO and bent normal of each texel from
//! the heights and the horizons the bake's kernel computes, in one pass with them
//! ([`SurfaceTap`] feeds them from the streamed horizon layers' own pass) or in a pass of
//! their own ([`bake_surface`]). The per-texel formulas and their oracles are
//! [`crate::terrain::surface`]; this module holds the bake's side: which maps and values to
//! keep, the row-by-row strips, and the maps' buffers.

use super::{check_scaled, make_kernel_for, resolve_radius, split, ResolvedRadius};
use crate::error::Result;
use crate::heightmap::HeightMap;
use crate::kernels::{self, Band, Grid, HorizonRows};
use crate::params::{BakeParams, Method};
use crate::progress::{Progress, Stage};
use std::sync::{Arc, Mutex};

/// What of the surface maps (SPEC §3.8) a bake keeps beside its horizons: none, their bytes
/// (8-bit files and textures), or their bytes and unquantised values (16-bit PNG, EXR).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Surface {
    None,
    Bytes,
    Values,
}

/// The surface maps of one bake (SPEC §3.8), encoded samples of `width × height` texels, row 0
/// first; each when asked. Holes are 0 in every map.
#[derive(Debug, Clone, Default)]
pub struct SurfaceMaps {
    pub width: usize,
    pub height: usize,
    /// RGB8: (n + 1) / 2, y as `normal_convention` says.
    pub normal: Option<Vec<u8>>,
    /// Grey8: the ambient occlusion.
    pub ao: Option<Vec<u8>>,
    /// RGB8 (`rgb`; `rg` with blue 0) or RGBA8 (`rgb_ao`) as `bent_normal_encoding` says.
    pub bent_normal: Option<Vec<u8>>,
    /// The same maps unquantised (what the bytes round), when the bake writes 16-bit PNGs or
    /// EXR: f32 in [0, 1], the channels as above.
    pub values: Option<SurfaceValues>,
}

/// The surface maps as f32 values in [0, 1] ((v + 1) / 2 for the vectors, the AO as it is),
/// each when asked, with the channels of [`SurfaceMaps`]'s bytes.
#[derive(Debug, Clone, Default)]
pub struct SurfaceValues {
    pub normal: Option<Vec<f32>>,
    pub ao: Option<Vec<f32>>,
    pub bent_normal: Option<Vec<f32>>,
}

/// The rows one call of [`SurfaceJob::rows`] fills: the bytes of the three maps, and their
/// values when the bake keeps those too.
type SurfaceOut<'o> = ([Option<&'o mut [u8]>; 3], [Option<&'o mut [f32]>; 3]);

impl SurfaceMaps {
    /// Channels per texel of `bent_normal` with `encoding`.
    pub fn bent_channels(encoding: crate::params::BentNormalEncoding) -> usize {
        use crate::params::BentNormalEncoding as E;
        match encoding {
            E::Rgb | E::Rg => 3,
            E::RgbAo => 4,
        }
    }
}

/// What the surface maps of one bake need of its parameters, computed once.
#[derive(Debug, Clone)]
pub struct SurfaceJob {
    outputs: crate::params::Outputs,
    flip_y: bool,
    encoding: crate::params::BentNormalEncoding,
    /// Per-bin horizons (ray methods) rather than the 8 channels (`lengyel`).
    per_bin: bool,
    /// The azimuths the horizons are at.
    dirs: crate::terrain::surface::BinDirs,
    bent_channels: usize,
    /// Keep the unquantised values too ([`SurfaceMaps::values`]).
    values: bool,
}

impl SurfaceJob {
    /// For `params`, whose kernel computes `bins` bins.
    pub fn new(params: &BakeParams, bins: usize) -> Self {
        use crate::terrain::surface;
        let per_bin = params.method != Method::Lengyel;
        SurfaceJob {
            outputs: params.outputs,
            flip_y: surface::flips_y(params.y_axis, params.normal_convention),
            encoding: params.bent_normal_encoding,
            per_bin,
            dirs: surface::BinDirs::new(if per_bin { bins } else { 8 }),
            bent_channels: SurfaceMaps::bent_channels(params.bent_normal_encoding),
            values: false,
        }
    }

    /// Keeps the unquantised values too (for 16-bit PNG and EXR files).
    pub fn with_values(mut self, values: bool) -> Self {
        self.values = values;
        self
    }

    /// Empty maps of `w × h` texels for what is asked.
    pub(super) fn maps(&self, w: usize, h: usize) -> SurfaceMaps {
        let o = self.outputs;
        SurfaceMaps {
            width: w,
            height: h,
            normal: o.normal.then(|| vec![0u8; w * h * 3]),
            ao: o.ao.then(|| vec![0u8; w * h]),
            bent_normal: o.bent_normal.then(|| vec![0u8; w * h * self.bent_channels]),
            values: self.values.then(|| SurfaceValues {
                normal: o.normal.then(|| vec![0f32; w * h * 3]),
                ao: o.ao.then(|| vec![0f32; w * h]),
                bent_normal: o.bent_normal.then(|| vec![0f32; w * h * self.bent_channels]),
            }),
        }
    }

    /// The surface samples of `rows` rows from `y0` (one texel after another) into the `out`
    /// slices of those rows, from the kernel's `channels` (8 per texel) or `bins` (`nb` per
    /// texel) of the same rows. Holes are left as they are (0).
    #[allow(clippy::too_many_arguments)]
    fn rows(
        &self,
        grid: &Grid<'_>,
        holes: Option<&[bool]>,
        y0: usize,
        rows: usize,
        channels: &[f32],
        bins: Option<&[f32]>,
        nb: usize,
        out: SurfaceOut<'_>,
    ) {
        // Compiled for AVX-512 where the CPU has it: the strips' f64 normals and encodings
        // then run 8 lanes a vector (the same IEEE operations, so the same bytes).
        #[cfg(target_arch = "x86_64")]
        if self.dirs.isa() == crate::kernels::isa::Isa::Avx512 {
            // SAFETY: `BinDirs` holds only a variant the CPU supports.
            return unsafe { self.rows_avx512(grid, holes, y0, rows, channels, bins, nb, out) };
        }
        self.rows_body(grid, holes, y0, rows, channels, bins, nb, out);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    #[allow(clippy::too_many_arguments)]
    unsafe fn rows_avx512(
        &self,
        grid: &Grid<'_>,
        holes: Option<&[bool]>,
        y0: usize,
        rows: usize,
        channels: &[f32],
        bins: Option<&[f32]>,
        nb: usize,
        out: SurfaceOut<'_>,
    ) {
        self.rows_body(grid, holes, y0, rows, channels, bins, nb, out);
    }

    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn rows_body(
        &self,
        grid: &Grid<'_>,
        holes: Option<&[bool]>,
        y0: usize,
        rows: usize,
        channels: &[f32],
        bins: Option<&[f32]>,
        nb: usize,
        out: SurfaceOut<'_>,
    ) {
        use crate::params::BentNormalEncoding;
        use crate::terrain::surface;
        let w = grid.width;
        let ch = self.bent_channels;
        let (mut out, mut vals) = out;
        let rg = self.encoding == BentNormalEncoding::Rg;
        let occluded =
            out[1].is_some() || out[2].is_some() || vals[1].is_some() || vals[2].is_some();
        let per = if self.per_bin && bins.is_some() { nb } else { 8 };
        let from = match bins {
            Some(b) if self.per_bin => b,
            _ => channels,
        };
        let (mut ao, mut bent) = ([0.0f32; surface::STRIP], surface::StripNormals::default());
        // A row at a time in strips of texels: their occlusion is one call, a lane per texel.
        for r in 0..rows {
            let y = y0 + r;
            for x0 in (0..w).step_by(surface::STRIP) {
                let lanes = surface::STRIP.min(w - x0);
                let mut nn = surface::StripNormals::default();
                let mut hole = [false; surface::STRIP];
                // Inside the map with no holes, the strip's normals at once.
                let mut strip = [[0.0; 3]; surface::STRIP];
                let whole =
                    holes.is_none() && surface::normals_strip(grid, x0, y, lanes, &mut strip);
                for l in 0..lanes {
                    let (x, t) = (x0 + l, r * w + x0 + l);
                    hole[l] = holes.is_some_and(|m| m[y * w + x]);
                    if hole[l] {
                        nn.z[l] = 1.0;
                        continue;
                    }
                    let n = if whole { strip[l] } else { surface::normal(grid, holes, x, y) };
                    (nn.x[l], nn.y[l], nn.z[l]) = (n[0] as f32, n[1] as f32, n[2] as f32);
                    if let Some(o) = out[0].as_deref_mut() {
                        o[t * 3..t * 3 + 3].copy_from_slice(&surface::encode_unit(n, self.flip_y));
                    }
                    if let Some(o) = vals[0].as_deref_mut() {
                        o[t * 3..t * 3 + 3].copy_from_slice(&surface::unit_values(n, self.flip_y));
                    }
                }
                if !occluded || hole[..lanes].iter().all(|&h| h) {
                    continue;
                }
                let k = (r * w + x0) * per;
                let s = &from[k..k + lanes * per];
                surface::occlusion_strip(s, lanes, &nn, &self.dirs, &mut ao, &mut bent);
                for l in (0..lanes).filter(|&l| !hole[l]) {
                    let t = r * w + x0 + l;
                    let a = f64::from(ao[l]);
                    let b = [f64::from(bent.x[l]), f64::from(bent.y[l]), f64::from(bent.z[l])];
                    if let Some(o) = out[1].as_deref_mut() {
                        o[t] = surface::encode_unorm(a);
                    }
                    if let Some(o) = vals[1].as_deref_mut() {
                        o[t] = ao[l];
                    }
                    if let Some(o) = out[2].as_deref_mut() {
                        let v = surface::encode_unit(b, self.flip_y);
                        let (z, a) = if rg { (0, 0) } else { (v[2], surface::encode_unorm(a)) };
                        o[t * ch..(t + 1) * ch].copy_from_slice(&[v[0], v[1], z, a][..ch]);
                    }
                    if let Some(o) = vals[2].as_deref_mut() {
                        let v = surface::unit_values(b, self.flip_y);
                        let (z, a) = if rg { (0.0, 0.0) } else { (v[2], ao[l]) };
                        o[t * ch..(t + 1) * ch].copy_from_slice(&[v[0], v[1], z, a][..ch]);
                    }
                }
            }
        }
    }
}

/// Bakes the surface maps `params.outputs` asks for (`normal`, `ao`, `bent_normal`, SPEC §3.8)
/// in one pass of the bake's kernel: each texel's normal from the scaled heights and its
/// occlusion from its horizons, the kernel's per-bin values for the ray methods and the 8
/// channel directions for `lengyel` (coarse: 45° apart, each a 5-bin average). With the
/// streamed horizon layers they come from the same pass instead ([`stream_horizon_tapped`]).
///
/// # Errors
/// [`crate::Error::Canceled`].
pub fn bake_surface(
    map: &HeightMap,
    params: &BakeParams,
    progress: &Progress,
) -> Result<(SurfaceMaps, ResolvedRadius)> {
    bake_surface_as(map, params, Surface::Bytes, progress)
}

/// [`bake_surface`], keeping the unquantised values too with [`Surface::Values`].
///
/// # Errors
/// [`crate::Error::Canceled`].
pub fn bake_surface_as(
    map: &HeightMap,
    params: &BakeParams,
    keep: Surface,
    progress: &Progress,
) -> Result<(SurfaceMaps, ResolvedRadius)> {
    let (w, h) = (map.width, map.height);
    let heights = map.scaled(params.height_scale);
    check_scaled(&heights)?;
    let radius = resolve_radius(params, w, h, &heights);
    let grid = Grid::new(w, h, &heights, params.edge, params.y_axis);
    let holes = map.terrain.holes.as_deref();
    let kernel = make_kernel_for(params, grid, radius.texels, progress, holes);
    let nb = kernel.bins();
    let job = SurfaceJob::new(params, nb).with_values(keep == Surface::Values);
    let mut maps = job.maps(w, h);
    let band = kernels::band_rows_for(kernel.as_ref());
    progress.start(Stage::Bake, h as u64);
    {
        let ch = job.bent_channels;
        let per = [3, 1, ch];
        let values = maps.values.as_mut();
        let [vn, va, vb] = match values {
            Some(v) => [v.normal.as_mut(), v.ao.as_mut(), v.bent_normal.as_mut()],
            None => [None, None, None],
        };
        let byte_rows = [maps.normal.as_mut(), maps.ao.as_mut(), maps.bent_normal.as_mut()];
        let byte_rows: Vec<Option<Vec<Mutex<&mut [u8]>>>> = byte_rows
            .into_iter()
            .zip(per)
            .map(|(m, c)| m.map(|p| split(p, band * w * c)))
            .collect();
        let value_rows: Vec<Option<Vec<Mutex<&mut [f32]>>>> = [vn, va, vb]
            .into_iter()
            .zip(per)
            .map(|(m, c)| m.map(|p| split(p, band * w * c)))
            .collect();
        kernels::run_bands(kernel.as_ref(), band, job.per_bin, progress, |bi, b: Band<'_>| {
            let mut bytes: Vec<_> =
                byte_rows.iter().map(|r| r.as_ref().and_then(|r| r[bi].lock().ok())).collect();
            let mut vals: Vec<_> =
                value_rows.iter().map(|r| r.as_ref().and_then(|r| r[bi].lock().ok())).collect();
            let mut it = bytes.iter_mut().map(|o| o.as_deref_mut().map(|s| &mut **s));
            let out = [it.next().flatten(), it.next().flatten(), it.next().flatten()];
            let mut it = vals.iter_mut().map(|o| o.as_deref_mut().map(|s| &mut **s));
            let val = [it.next().flatten(), it.next().flatten(), it.next().flatten()];
            job.rows(&grid, holes, b.y0, b.rows, b.channels, b.bins, nb, (out, val));
        })?;
    }
    Ok((maps, radius))
}

/// A kernel whose rows also feed the surface maps: the horizons it computes for the horizon
/// layers (their channels, or the bins asked of it anyway) give each texel's occlusion in the
/// same pass, so `outputs=horizon,normal,ao,bent_normal` costs one kernel pass, not two.
pub(super) struct SurfaceTap<'a> {
    pub(super) inner: Box<dyn HorizonRows + 'a>,
    pub(super) grid: Grid<'a>,
    pub(super) holes: Option<&'a [bool]>,
    pub(super) job: SurfaceJob,
    pub(super) maps: Arc<Mutex<SurfaceMaps>>,
}

impl HorizonRows for SurfaceTap<'_> {
    forward_to_inner!();
    fn rows(&self, y0: usize, channels: &mut [f32], bins_out: Option<&mut [f32]>) {
        let w = self.grid.width;
        let (rows, nb) = (channels.len() / (w * 8), self.inner.bins());
        // The per-bin values when the surface needs them and the caller did not ask: one
        // band's worth, the kernel's own output, in buffers each pool thread keeps (a band is
        // megabytes: allocating and zeroing it per band cost as much as the occlusion). A stack
        // of them, since a thread waiting inside the kernel may run another band meanwhile.
        thread_local! {
            static OWN: std::cell::RefCell<Vec<Vec<f32>>> = const { std::cell::RefCell::new(Vec::new()) };
        }
        let mut own = OWN.with(|o| o.borrow_mut().pop()).unwrap_or_default();
        let mut bins: Option<&mut [f32]> = match bins_out {
            Some(b) => Some(b),
            None if self.job.per_bin => {
                if own.len() < rows * w * nb {
                    own.resize(rows * w * nb, 0.0);
                }
                Some(&mut own[..rows * w * nb])
            }
            None => None,
        };
        self.inner.rows(y0, channels, bins.as_deref_mut());
        if self.inner.failure().is_some() {
            return;
        }
        let mut band = self.job.maps(w, rows);
        let out =
            [band.normal.as_deref_mut(), band.ao.as_deref_mut(), band.bent_normal.as_deref_mut()];
        let val = match band.values.as_mut() {
            Some(v) => [v.normal.as_deref_mut(), v.ao.as_deref_mut(), v.bent_normal.as_deref_mut()],
            None => [None, None, None],
        };
        self.job.rows(&self.grid, self.holes, y0, rows, channels, bins.as_deref(), nb, (out, val));
        let mut maps = self.maps.lock().unwrap_or_else(|e| e.into_inner());
        let ch = self.job.bent_channels;
        fn put<V: Copy>(to: &mut Option<Vec<V>>, from: Option<Vec<V>>, at: usize) {
            if let (Some(to), Some(from)) = (to.as_mut(), from) {
                to[at..at + from.len()].copy_from_slice(&from);
            }
        }
        let at = y0 * w;
        put(&mut maps.normal, band.normal.take(), at * 3);
        put(&mut maps.ao, band.ao.take(), at);
        put(&mut maps.bent_normal, band.bent_normal.take(), at * ch);
        if let (Some(to), Some(from)) = (maps.values.as_mut(), band.values.take()) {
            put(&mut to.normal, from.normal, at * 3);
            put(&mut to.ao, from.ao, at);
            put(&mut to.bent_normal, from.bent_normal, at * ch);
        }
        drop(maps);
        OWN.with(|o| {
            let mut kept = o.borrow_mut();
            if kept.len() < 4 {
                kept.push(own);
            }
        });
    }
}
