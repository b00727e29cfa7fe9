//! One bake: resolved parameters → kernel → quantised horizon layers, with progress and cancel.
//!
//! This is the only place that knows which kernel a method means and which precisions the
//! requested output formats need. The kernel's rows are streamed band by band straight into the
//! 8-bit, 16-bit or f32 layer buffers that were asked for, so the f32 working set is one band per
//! thread (SPEC §3, issue "fast kernels": an 8192² bake never holds eight f32 planes).
//!
//! [`stream_horizon`] goes one step further for outputs that can be written row by row (PNG):
//! bands are handed to a sink in row order, a window at a time, so not even the quantised layers
//! exist whole, and the height map is scaled in place instead of copied.

use crate::error::Result;
use crate::heightmap::HeightMap;
use crate::kernels::{self, Band, Grid, HorizonRows};
use crate::params::{AzimuthFrom, BakeParams, Encoding, Method, Radius};
use crate::progress::{Progress, Stage};
use serde::Serialize;
use std::sync::{Arc, Mutex};

pub use crate::layers::{HorizonLayers, Precisions, Sample};

mod rays;
pub use rays::{centre_lat_lon, compass_of, horizon_profile, shadow, MAX_SUN_RAYS};

/// How the radius was resolved (reported with the bake).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ResolvedRadius {
    /// The radius in texels the kernel used.
    pub texels: u32,
    /// Why (for `auto` and `unlimited`).
    pub reason: String,
}

/// Resolves `radius` for a map: `auto` from the height range and `min_elevation_deg` (SPEC §3.6),
/// `unlimited` to max(W, H).
pub fn resolve_radius(
    params: &BakeParams,
    width: usize,
    height: usize,
    heights: &[f32],
) -> ResolvedRadius {
    resolve_radius_in(params, width, height, || {
        Grid::new(width, height, heights, params.edge, params.y_axis).range()
    })
}

/// [`resolve_radius`] with the map's scaled height range given by `range` (asked only for
/// `auto`): a tiled bake resolves it once, on the whole map's range (SPEC §7.1).
pub fn resolve_radius_in(
    params: &BakeParams,
    width: usize,
    height: usize,
    range: impl FnOnce() -> (f32, f32),
) -> ResolvedRadius {
    let cap = width.max(height).max(1) as u32;
    if let (Some(d), Some(cell)) = (params.max_distance, params.cell_size) {
        // SPEC §3.7: ceil(max_distance / cell_size) texels (capped like a fixed radius).
        let raw = (d / cell * (1.0 - 1e-12)).ceil();
        let texels = raw.clamp(1.0, crate::params::MAX_RADIUS.max(cap) as f64) as u32;
        return ResolvedRadius {
            texels,
            reason: format!("max_distance: ceil({d} / cell_size {cell}) = {texels} texels"),
        };
    }
    match params.radius {
        Radius::Texels(r) => ResolvedRadius { texels: r, reason: "as requested".into() },
        Radius::Unlimited => {
            ResolvedRadius { texels: cap, reason: format!("unlimited: max(W, H) = {cap} texels") }
        }
        Radius::Auto => {
            let (lo, hi) = range();
            let dh = (hi - lo) as f64;
            let tan = params.min_elevation_deg.to_radians().tan();
            // tan 45° is 0.9999999999999999 in f64: without the relative slack, Δh = 10 texels
            // at 45° would resolve to 11 instead of SPEC §3.6's ceil(10 / 1) = 10.
            let raw = (dh / tan * (1.0 - 1e-12)).ceil();
            let texels =
                if raw.is_finite() { (raw as u64).clamp(1, cap as u64) as u32 } else { cap };
            ResolvedRadius {
                texels,
                reason: format!(
                    "auto: height range {dh:.4} texels / tan({}°) = {:.2}, capped at {cap}",
                    params.min_elevation_deg,
                    dh / tan
                ),
            }
        }
    }
}

/// Builds the kernel a method and resolved radius mean.
/// Kernels that can stop inside a band watch `progress` for a cancel.
pub fn make_kernel<'a>(
    params: &BakeParams,
    grid: Grid<'a>,
    radius: u32,
    progress: &Progress,
) -> Box<dyn HorizonRows + 'a> {
    make_kernel_for(params, grid, radius, progress, None)
}

/// Refuses a method whose storage grows with the whole map × bins (`sweep`'s far-field table,
/// in memory or spilled to a temporary file) on a map where it would not fit even on disk
/// ([`kernels::sweep::check_memory`]). The decode and the probes resolve the parameters; every
/// caller then asks this before it bakes or accepts a bake.
///
/// # Errors
/// [`Error::Param`] naming `method`.
pub fn check_method_fits(params: &BakeParams, width: u32, height: u32) -> Result<()> {
    if params.method == Method::Sweep && needs_table(params) {
        kernels::sweep::check_memory(width, height, params.bins)?;
    }
    Ok(())
}

/// Whether a `sweep` bake keeps its far-field table (W·H·bins, in memory or on disk): every
/// output taken from its bands does (the horizon layers, Fourier, the surface maps, a
/// `tilted` SVF); `angles` and a plain SVF alone come from its planes instead
/// ([`kernels::sweep::Sweep::planes`]), whose memory does not grow with the bins.
pub fn needs_table(params: &BakeParams) -> bool {
    let o = &params.outputs;
    o.horizon || o.fourier || o.normal || o.ao || o.bent_normal || !azimuth_major(params)
}

/// Settles the method of a bake of a `width`×`height` map, `tiled` when it is above
/// `--tile-above`: a `sweep` the DEM defaults chose (SPEC §2; not given by the user) becomes
/// `exact` where `sweep` cannot run (its far field would not fit even on disk, or the map is
/// baked in tiles), then [`check_method_fits`]. The method is then marked given, so the
/// parameters the bake stores replay to the same choice.
///
/// # Errors
/// As [`check_method_fits`].
pub fn fit_method(params: &mut BakeParams, width: u32, height: u32, tiled: bool) -> Result<()> {
    if params.method == Method::Sweep && !params.explicit.has("method") {
        let fits = !tiled
            && (!needs_table(params)
                || kernels::sweep::check_memory(width, height, params.bins).is_ok());
        params.set("method", if fits { "sweep" } else { "exact" })?;
    }
    check_method_fits(params, width, height)
}

/// [`make_kernel`] for a map with nodata `holes`: `exact` skips the cells that touch a hole
/// exactly (SPEC §2); the other methods see the holes' fill far below the map
/// ([`crate::heightmap::HOLE_DEPTH`]); `march` takes the exact walk within its near reach of
/// one ([`kernels::march::March::with_holes`]), and `sweep`'s near field skips the cells that
/// touch one itself ([`kernels::sweep::Sweep::with_holes`]). Outputs at holes are masked by the
/// callers.
pub fn make_kernel_for<'a>(
    params: &BakeParams,
    grid: Grid<'a>,
    radius: u32,
    progress: &Progress,
    holes: Option<&'a [bool]>,
) -> Box<dyn HorizonRows + 'a> {
    match params.method {
        Method::Lengyel => Box::new(
            kernels::lengyel::LengyelFast::new(grid, radius, params.bins).with_cancel(progress),
        ),
        Method::Exact => {
            // Unlimited means "to the map edge" with edge=none, which can be longer than
            // max(W, H) on a diagonal; the kernel resolves it itself.
            let r = (params.radius != Radius::Unlimited || params.max_distance.is_some())
                .then_some(radius);
            Box::new(
                kernels::exact::ExactHorizon::new(grid, r, params.bins, params.reduce)
                    .with_cancel(progress)
                    .with_curvature(curvature(params))
                    .with_holes(holes),
            )
        }
        // Cost independent of R: `unlimited` is the kernel's own (to the edge with edge=none).
        Method::Sweep => Box::new(sweep_kernel(params, grid, radius, progress, holes, false)),
        // `unlimited` is max(W, H) texels here, as for Lengyel: a march's cost grows with R.
        Method::March => Box::new(
            kernels::march::March::new(grid, radius, params.bins, params.reduce)
                .with_cancel(progress)
                .with_curvature(curvature(params))
                .with_holes(holes),
        ),
    }
}

/// The `sweep` kernel of [`make_kernel_for`]; `azimuth_major`: built to give its horizons plane
/// by plane ([`kernels::sweep::Sweep::planes`]), with no far-field table in memory or on disk.
fn sweep_kernel<'a>(
    params: &BakeParams,
    grid: Grid<'a>,
    radius: u32,
    progress: &Progress,
    holes: Option<&'a [bool]>,
    azimuth_major: bool,
) -> kernels::sweep::Sweep<'a> {
    let r = (params.radius != Radius::Unlimited || params.max_distance.is_some()).then_some(radius);
    let (w, h) = (grid.width as u32, grid.height as u32);
    let spill = (!azimuth_major && kernels::sweep::spills(w, h, params.bins)).then(|| {
        Arc::new(FileSpill::new(grid.width * grid.height, progress.scratch_dir()))
            as Arc<dyn kernels::sweep::FarSpill>
    });
    let opt = kernels::sweep::Options {
        curvature: curvature(params),
        isa: None,
        progress: Some(progress.clone()),
        spill,
        azimuth_major,
    };
    kernels::sweep::Sweep::with_options(grid, r, params.bins, params.reduce, opt).with_holes(holes)
}

/// `sweep`'s far field in a temporary file, one plane of `plane` f32 per bin at offset
/// `n · plane · 4` (native byte order: the file never leaves the process). The file is created
/// unlinked on first use ([`tempfile::tempfile_in`]), so it is gone when the kernel is dropped
/// or the process dies, and written and read with positioned I/O, so the sweeps of several
/// azimuths and the bands of several threads use it at once without a lock.
pub struct FileSpill {
    plane: usize,
    dir: std::path::PathBuf,
    file: std::sync::OnceLock<std::result::Result<std::fs::File, String>>,
}

impl FileSpill {
    /// A spill for planes of `plane` values, in a file in `dir` (made on first use).
    pub fn new(plane: usize, dir: std::path::PathBuf) -> FileSpill {
        FileSpill { plane, dir, file: std::sync::OnceLock::new() }
    }

    fn file(&self) -> std::io::Result<&std::fs::File> {
        let made = self.file.get_or_init(|| {
            let dir = &self.dir;
            std::fs::create_dir_all(dir)
                .and_then(|()| tempfile::tempfile_in(dir))
                .map_err(|e| format!("cannot create a temporary file in {}: {e}", dir.display()))
        });
        made.as_ref().map_err(|e| std::io::Error::other(e.clone()))
    }
}

impl kernels::sweep::FarSpill for FileSpill {
    fn put(&self, n: usize, start: usize, values: &[f32]) -> std::io::Result<()> {
        use std::os::unix::fs::FileExt;
        let file = self.file()?;
        let mut off = ((n * self.plane + start) * 4) as u64;
        // In pieces of 1 MiB, so the byte copy stays small.
        let mut bytes = Vec::with_capacity(values.len().min(1 << 18) * 4);
        for piece in values.chunks(1 << 18) {
            bytes.clear();
            bytes.extend(piece.iter().flat_map(|v| v.to_ne_bytes()));
            file.write_all_at(&bytes, off)?;
            off += bytes.len() as u64;
        }
        Ok(())
    }

    fn get(&self, n: usize, start: usize, out: &mut [f32]) -> std::io::Result<()> {
        use std::os::unix::fs::FileExt;
        let file = self.file()?;
        let mut off = ((n * self.plane + start) * 4) as u64;
        let mut bytes = vec![0u8; out.len().min(1 << 18) * 4];
        for piece in out.chunks_mut(1 << 18) {
            let b = &mut bytes[..piece.len() * 4];
            file.read_exact_at(b, off)?;
            for (v, c) in piece.iter_mut().zip(b.chunks_exact(4)) {
                *v = f32::from_ne_bytes([c[0], c[1], c[2], c[3]]);
            }
            off += b.len() as u64;
        }
        Ok(())
    }
}

/// Mean earth radius, metres (SPEC §3.7).
pub const EARTH_RADIUS_M: f64 = 6_371_000.0;

/// The earth-curvature drop per texel² in texels (0 when off or without a cell size): a point s
/// texels away is s·cell·u metres away (u metres per map unit) and drops (s·cell·u)² / (2 R_e)
/// metres, which is that / u map units of height, times `height_scale` texels, R_e = 6 371 km /
/// (1 − refraction).
pub fn curvature(params: &BakeParams) -> f64 {
    match (params.earth_curvature, params.cell_size) {
        (crate::params::EarthCurvature::On, Some(cell)) => {
            let re = EARTH_RADIUS_M / (1.0 - params.refraction);
            cell * cell * params.linear_unit_m * params.height_scale / (2.0 * re)
        }
        _ => 0.0,
    }
}

/// A kernel whose outputs at hole texels (SPEC §2 "Nodata") are 0, channels and bins alike.
pub struct Masked<'a> {
    inner: Box<dyn HorizonRows + 'a>,
    holes: &'a [bool],
}

/// The [`HorizonRows`] methods a wrapper kernel (`inner` and something done to its rows)
/// forwards unchanged.
macro_rules! forward_to_inner {
    () => {
        fn width(&self) -> usize {
            self.inner.width()
        }
        fn height(&self) -> usize {
            self.inner.height()
        }
        fn bins(&self) -> usize {
            self.inner.bins()
        }
        fn texel_cost(&self) -> f64 {
            self.inner.texel_cost()
        }
        fn failure(&self) -> Option<crate::Error> {
            self.inner.failure()
        }
    };
}

/// `kernel`, masked where `holes` says (unchanged without holes).
pub fn masked<'a>(
    kernel: Box<dyn HorizonRows + 'a>,
    holes: Option<&'a [bool]>,
) -> Box<dyn HorizonRows + 'a> {
    match holes {
        Some(holes) => Box::new(Masked { inner: kernel, holes }),
        None => kernel,
    }
}

impl HorizonRows for Masked<'_> {
    forward_to_inner!();
    fn rows(&self, y0: usize, channels: &mut [f32], mut bins_out: Option<&mut [f32]>) {
        self.inner.rows(y0, channels, bins_out.as_deref_mut());
        let (w, nb) = (self.width(), self.bins());
        let start = y0 * w;
        for (k, ch) in channels.chunks_exact_mut(8).enumerate() {
            if self.holes[start + k] {
                ch.fill(0.0);
                if let Some(bo) = bins_out.as_deref_mut() {
                    bo[k * nb..(k + 1) * nb].fill(0.0);
                }
            }
        }
    }
}

/// Runs the horizon kernel over `map` and quantises straight into the requested precisions.
///
/// # Errors
/// [`crate::Error::Canceled`] when `progress` is canceled.
pub fn bake_horizon(
    map: &HeightMap,
    params: &BakeParams,
    precisions: Precisions,
    progress: &Progress,
) -> Result<(HorizonLayers, ResolvedRadius)> {
    let heights = map.scaled(params.height_scale);
    check_scaled(&heights)?;
    let radius = resolve_radius(params, map.width, map.height, &heights);
    let grid = Grid::new(map.width, map.height, &heights, params.edge, params.y_axis);
    let kernel =
        make_kernel_for(params, grid, radius.texels, progress, map.terrain.holes.as_deref());
    let kernel = masked(kernel, map.terrain.holes.as_deref());
    progress.start(Stage::Bake, map.height as u64);
    let layers = run_into_layers(kernel.as_ref(), params.encoding, precisions, progress)?;
    Ok((layers, radius))
}

/// A kernel restricted to rows `oy .. oy + rows` of `inner`: a tile's interior rows inside
/// its window (the halo rows are read, never computed).
struct RowWindow<'a> {
    inner: Box<dyn HorizonRows + 'a>,
    oy: usize,
    rows: usize,
}

impl HorizonRows for RowWindow<'_> {
    fn width(&self) -> usize {
        self.inner.width()
    }
    fn height(&self) -> usize {
        self.rows
    }
    fn bins(&self) -> usize {
        self.inner.bins()
    }
    fn texel_cost(&self) -> f64 {
        self.inner.texel_cost()
    }
    fn failure(&self) -> Option<crate::Error> {
        self.inner.failure()
    }
    fn rows(&self, y0: usize, channels: &mut [f32], bins_out: Option<&mut [f32]>) {
        self.inner.rows(self.oy + y0, channels, bins_out);
    }
}

/// Bakes the interior of one tile of a tiled bake (SPEC §7.1): `window` is the tile's window of
/// the map (interior + halo, unscaled values and holes as the whole map's decode has them),
/// `interior` = (column, row, width, height) of the interior inside the window, `range` the
/// whole map's scaled height range and `radius` the radius resolved on the whole map. Returns
/// the interior's layers at `precisions`: per texel the same values as the untiled bake.
///
/// # Errors
/// [`crate::Error::Canceled`] when `progress` is canceled.
pub fn bake_window(
    window: HeightMap,
    params: &BakeParams,
    interior: (usize, usize, usize, usize),
    range: (f32, f32),
    radius: u32,
    precisions: Precisions,
    progress: &Progress,
) -> Result<HorizonLayers> {
    let (ww, wh) = (window.width, window.height);
    let (ox, oy, iw, ih) = interior;
    assert!(ox + iw <= ww && oy + ih <= wh, "interior outside its window");
    let mut window = window;
    let holes = window.terrain.holes.take();
    let heights = window.into_scaled(params.height_scale);
    let grid = Grid::new(ww, wh, &heights, params.edge, params.y_axis).with_range(range.0, range.1);
    let kernel = make_kernel_for(params, grid, radius, progress, holes.as_deref());
    let kernel = masked(kernel, holes.as_deref());
    let rows = RowWindow { inner: kernel, oy, rows: ih };
    progress.start(Stage::Bake, ih as u64);
    let full = run_into_layers(&rows, params.encoding, precisions, progress)?;
    // Keep the interior's columns.
    fn cut<T: Copy>(
        layers: Option<[Vec<T>; 2]>,
        ww: usize,
        ox: usize,
        iw: usize,
    ) -> Option<[Vec<T>; 2]> {
        layers.map(|ls| {
            ls.map(|l| {
                l.chunks_exact(ww * 4)
                    .flat_map(|row| row[ox * 4..(ox + iw) * 4].iter().copied())
                    .collect()
            })
        })
    }
    Ok(HorizonLayers {
        width: iw,
        height: ih,
        u8: cut(full.u8, ww, ox, iw),
        u16: cut(full.u16, ww, ox, iw),
        f32: cut(full.f32, ww, ox, iw),
    })
}

/// Kernels take height differences in f32: the scaled heights and their range must be finite.
///
/// # Errors
/// [`crate::Error::Param`] naming `height_scale` when they are not.
pub fn check_scaled(heights: &[f32]) -> Result<()> {
    let (lo, hi) =
        heights.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), &v| (l.min(v), h.max(v)));
    if heights.is_empty() || (hi - lo).is_finite() {
        return Ok(());
    }
    Err(crate::Error::param(
        "height_scale",
        format!(
            "heights × height_scale span {lo:e} to {hi:e} texels, beyond the f32 range; \
             use a smaller height_scale"
        ),
    ))
}

/// Splits `buf` (two layers of `h·w·4`) into per-band chunks, one lock each (never contended:
/// each band index is written once).
fn split<T>(buf: &mut [T], per_band: usize) -> Vec<Mutex<&mut [T]>> {
    buf.chunks_mut(per_band.max(1)).map(Mutex::new).collect()
}

/// Streams `kernel` band by band into layer buffers.
///
/// # Errors
/// [`crate::Error::Canceled`].
pub fn run_into_layers<K: HorizonRows + ?Sized>(
    kernel: &K,
    encoding: Encoding,
    precisions: Precisions,
    progress: &Progress,
) -> Result<HorizonLayers> {
    let (w, h) = (kernel.width(), kernel.height());
    let n = w * h * 4;
    let mut u8s = precisions.u8.then(|| [vec![0u8; n], vec![0u8; n]]);
    let mut u16s = precisions.u16.then(|| [vec![0u16; n], vec![0u16; n]]);
    let mut f32s = precisions.f32.then(|| [vec![0f32; n], vec![0f32; n]]);
    let band = kernels::band_rows_for(kernel);
    let per_band = band * w * 4;
    {
        let b8 = u8s.as_mut().map(|[a, b]| [split(a, per_band), split(b, per_band)]);
        let b16 = u16s.as_mut().map(|[a, b]| [split(a, per_band), split(b, per_band)]);
        let b32 = f32s.as_mut().map(|[a, b]| [split(a, per_band), split(b, per_band)]);
        let sqrt = encoding == Encoding::Sqrt;
        kernels::run_bands(kernel, band, false, progress, |bi, band: Band<'_>| {
            for layer in 0..2 {
                let vals = || {
                    band.channels.chunks_exact(8).flat_map(move |t| {
                        t[layer * 4..layer * 4 + 4].iter().map(move |&s| {
                            if sqrt {
                                s.max(0.0).sqrt()
                            } else {
                                s
                            }
                        })
                    })
                };
                if let Some(b) = &b8 {
                    if let Ok(mut dst) = b[layer][bi].lock() {
                        for (d, v) in dst.iter_mut().zip(vals()) {
                            *d = crate::layers::quantize8(v);
                        }
                    }
                }
                if let Some(b) = &b16 {
                    if let Ok(mut dst) = b[layer][bi].lock() {
                        for (d, v) in dst.iter_mut().zip(vals()) {
                            *d = crate::layers::quantize16(v);
                        }
                    }
                }
                if let Some(b) = &b32 {
                    if let Ok(mut dst) = b[layer][bi].lock() {
                        for (d, v) in dst.iter_mut().zip(vals()) {
                            *d = v;
                        }
                    }
                }
            }
        })?;
    }
    Ok(HorizonLayers { width: w, height: h, u8: u8s, u16: u16s, f32: f32s })
}

/// One finished band as [`stream_rows`] hands it on: image rows `y0 .. y0 + rows` of both RGBA
/// layers, `rows · width · 4` samples each, row-major.
#[derive(Debug, Clone, Copy)]
pub struct LayerRows<'a, T> {
    pub y0: usize,
    pub rows: usize,
    pub layers: [&'a [T]; 2],
}

/// Bakes `map` like [`bake_horizon`] but hands the quantised rows of both layers to `sink` band
/// by band, in row order, instead of collecting whole layers: with a sink that encodes as it goes
/// (a row-streaming PNG writer) the only full-size buffer alive is the height map itself, which
/// is taken by value and scaled in place.
///
/// # Errors
/// [`crate::Error::Canceled`] when `progress` is canceled; whatever `sink` returns.
pub fn stream_horizon<T, S>(
    map: HeightMap,
    params: &BakeParams,
    progress: &Progress,
    sink: S,
) -> Result<ResolvedRadius>
where
    T: Sample,
    S: FnMut(LayerRows<'_, T>) -> Result<()> + Send,
{
    Ok(stream_horizon_tapped(map, params, Surface::None, progress, sink)?.0)
}

/// [`stream_horizon`], and unless `surface` is [`Surface::None`] the surface maps
/// `params.outputs` asks for (SPEC §3.8) from the same kernel pass (each band's horizons feed
/// them as they are computed).
///
/// # Errors
/// As [`stream_horizon`].
pub fn stream_horizon_tapped<T, S>(
    map: HeightMap,
    params: &BakeParams,
    surface: Surface,
    progress: &Progress,
    sink: S,
) -> Result<(ResolvedRadius, Option<SurfaceMaps>)>
where
    T: Sample,
    S: FnMut(LayerRows<'_, T>) -> Result<()> + Send,
{
    let (w, h) = (map.width, map.height);
    let mut map = map;
    let holes = map.terrain.holes.take();
    let heights = map.into_scaled(params.height_scale);
    let radius = resolve_radius(params, w, h, &heights);
    let grid = Grid::new(w, h, &heights, params.edge, params.y_axis);
    let mut kernel = make_kernel_for(params, grid, radius.texels, progress, holes.as_deref());
    let mut maps = None;
    if surface != Surface::None {
        let job = SurfaceJob::new(params, kernel.bins()).with_values(surface == Surface::Values);
        let shared = Arc::new(Mutex::new(job.maps(w, h)));
        maps = Some(shared.clone());
        let holes = holes.as_deref();
        kernel = Box::new(SurfaceTap { inner: kernel, grid, holes, job, maps: shared });
    }
    let kernel = masked(kernel, holes.as_deref());
    progress.start(Stage::Bake, h as u64);
    stream_rows(kernel.as_ref(), params.encoding, progress, sink)?;
    let maps = maps.map(|m| std::mem::take(&mut *m.lock().unwrap_or_else(|e| e.into_inner())));
    Ok((radius, maps))
}

/// Quantised rows of a window of consecutive bands, both layers: band `i` of the window owns
/// `2 · band · width · 4` samples (layer 0 rows, then layer 1 rows).
struct Window<T> {
    samples: Vec<T>,
    /// First band of the window and how many bands it holds.
    first: usize,
    count: usize,
}

/// Runs `kernel` over a window of bands in parallel and quantises them into `win`. Checks for a
/// cancel before and after each band as [`kernels::run_bands`] does.
fn compute_window<T: Sample, K: HorizonRows + ?Sized>(
    kernel: &K,
    sqrt: bool,
    band: usize,
    first: usize,
    scratch: &mut [f32],
    win: &mut Window<T>,
    progress: &Progress,
) -> Result<()> {
    use rayon::prelude::*;
    let (w, h) = (kernel.width(), kernel.height());
    let nbands = h.div_ceil(band);
    let count = (scratch.len() / (band * w * 8)).min(nbands - first);
    win.first = first;
    win.count = count;
    let per_band = 2 * band * w * 4;
    scratch
        .par_chunks_mut(band * w * 8)
        .zip(win.samples.par_chunks_mut(per_band))
        .take(count)
        .enumerate()
        .try_for_each(|(i, (ch, out))| {
            if progress.is_canceled() {
                return Err(crate::Error::Canceled);
            }
            let y0 = (first + i) * band;
            let rows = band.min(h - y0);
            let ch = &mut ch[..rows * w * 8];
            kernel.rows(y0, ch, None);
            // A kernel may return early on cancel or a failure; never hand its partial band on.
            if let Some(e) = kernel.failure() {
                return Err(e);
            }
            if progress.is_canceled() {
                return Err(crate::Error::Canceled);
            }
            let (l0, l1) = out.split_at_mut(band * w * 4);
            for ((t, a), b) in
                ch.chunks_exact(8).zip(l0.chunks_exact_mut(4)).zip(l1.chunks_exact_mut(4))
            {
                for k in 0..4 {
                    let (v0, v1) = if sqrt {
                        (t[k].max(0.0).sqrt(), t[4 + k].max(0.0).sqrt())
                    } else {
                        (t[k], t[4 + k])
                    };
                    a[k] = T::quantize(v0);
                    b[k] = T::quantize(v1);
                }
            }
            Ok(())
        })
}

/// Hands the bands of `win` to `sink` in order, advancing `progress` by each band's rows.
fn drain_window<T: Sample, S>(
    win: &Window<T>,
    band: usize,
    (w, h): (usize, usize),
    progress: &Progress,
    sink: &mut S,
) -> Result<()>
where
    S: FnMut(LayerRows<'_, T>) -> Result<()>,
{
    let per_band = 2 * band * w * 4;
    for i in 0..win.count {
        if progress.is_canceled() {
            return Err(crate::Error::Canceled);
        }
        let y0 = (win.first + i) * band;
        let rows = band.min(h - y0);
        let out = &win.samples[i * per_band..(i + 1) * per_band];
        let n = rows * w * 4;
        let layers = [&out[..n], &out[band * w * 4..band * w * 4 + n]];
        sink(LayerRows { y0, rows, layers })?;
        progress.advance(rows as u64);
    }
    Ok(())
}

/// Streams `kernel` into `sink` in row order: windows of `2 × threads` bands are computed in
/// parallel, then handed on band by band while the next window is being computed (so an
/// encoder in the sink overlaps the kernel; the PNG writer's own parallel deflate runs on the
/// same pool). Memory: two windows of quantised
/// rows and one window of f32 channels, whatever the map size.
///
/// Progress advances by a band's rows once the sink has taken it; a cancel is checked before
/// and after each band is computed and before each is handed on.
///
/// # Errors
/// [`crate::Error::Canceled`]; whatever `sink` returns (no band is handed on after an error).
pub fn stream_rows<T, K, S>(
    kernel: &K,
    encoding: Encoding,
    progress: &Progress,
    mut sink: S,
) -> Result<()>
where
    T: Sample,
    K: HorizonRows + ?Sized,
    S: FnMut(LayerRows<'_, T>) -> Result<()> + Send,
{
    let (w, h) = (kernel.width(), kernel.height());
    if w == 0 || h == 0 {
        return Ok(());
    }
    let band = kernels::band_rows_for(kernel);
    let nbands = h.div_ceil(band);
    let window = (2 * rayon::current_num_threads()).clamp(1, nbands);
    let sqrt = encoding == Encoding::Sqrt;
    let mut scratch = vec![0f32; window * band * w * 8];
    let new_window =
        || Window { samples: vec![T::default(); window * 2 * band * w * 4], first: 0, count: 0 };
    let (mut front, mut back) = (new_window(), new_window());
    compute_window(kernel, sqrt, band, 0, &mut scratch, &mut front, progress)?;
    loop {
        let next = front.first + front.count;
        let (drained, computed) = rayon::join(
            || drain_window(&front, band, (w, h), progress, &mut sink),
            || {
                if next < nbands {
                    compute_window(kernel, sqrt, band, next, &mut scratch, &mut back, progress)
                        .map(|()| true)
                } else {
                    Ok(false)
                }
            },
        );
        drained?;
        if !computed? {
            return Ok(());
        }
        std::mem::swap(&mut front, &mut back);
    }
}

/// Interleaves two RGBA f32 layers back into `H·W·8` channel order (golden-file layout).
pub fn layers_to_channels(layers: &[Vec<f32>; 2]) -> Vec<f32> {
    let mut out = Vec::with_capacity(layers[0].len() * 2);
    for (a, b) in layers[0].chunks_exact(4).zip(layers[1].chunks_exact(4)) {
        out.extend_from_slice(a);
        out.extend_from_slice(b);
    }
    out
}

/// Bakes the Fourier horizon encoding (SPEC §3.4): the kernel's per-bin horizon s(φ_n) of each
/// band is projected on `fourier_terms` basis functions and stored companded in 8-bit layers
/// (layout and formulas in [`kernels::fourier`]). `encoding` does not apply: the coefficients
/// have their own companding.
///
/// # Errors
/// [`crate::Error::Canceled`] when `progress` is canceled.
pub fn bake_fourier(
    map: &HeightMap,
    params: &BakeParams,
    progress: &Progress,
) -> Result<(kernels::fourier::FourierLayers, ResolvedRadius)> {
    use kernels::fourier::{encode_texel, FourierLayers, Projector, MAX_TERMS};
    let heights = map.scaled(params.height_scale);
    check_scaled(&heights)?;
    let radius = resolve_radius(params, map.width, map.height, &heights);
    let grid = Grid::new(map.width, map.height, &heights, params.edge, params.y_axis);
    let kernel =
        make_kernel_for(params, grid, radius.texels, progress, map.terrain.holes.as_deref());
    let kernel = masked(kernel, map.terrain.holes.as_deref());
    let (w, h, nb) = (kernel.width(), kernel.height(), kernel.bins());
    let terms = params.fourier_terms as usize;
    let range = params.fourier_range;
    let projector = Projector::new(nb, terms);
    let mut bands = vec![0u8; w * h * 4];
    let mut constant = vec![0u8; w * h];
    let mut high = (terms > 5).then(|| vec![0u8; w * h * 4]);
    let band = kernels::band_rows_for(kernel.as_ref());
    progress.start(Stage::Fourier, h as u64);
    {
        let b4 = split(&mut bands, band * w * 4);
        let b1 = split(&mut constant, band * w);
        let bh = high.as_mut().map(|v| split(v, band * w * 4));
        kernels::run_bands(kernel.as_ref(), band, true, progress, |bi, band: Band<'_>| {
            let Some(bins) = band.bins else { return };
            let (Ok(mut d4), Ok(mut d1)) = (b4[bi].lock(), b1[bi].lock()) else { return };
            let mut dh = bh.as_ref().and_then(|v| v[bi].lock().ok());
            let mut c = [0.0f64; MAX_TERMS];
            for (t, s) in bins.chunks_exact(nb).enumerate() {
                projector.project(s, &mut c);
                let hi = dh.as_mut().map(|d| &mut d[t * 4..t * 4 + 4]);
                encode_texel(&c, terms, range, &mut d4[t * 4..t * 4 + 4], &mut d1[t], hi);
            }
        })?;
    }
    Ok((FourierLayers { width: w, height: h, terms, range, bands, constant, high }, radius))
}

mod terrain;
use terrain::azimuth_major;
pub use terrain::MAX_ANGLE_VALUES;
pub use terrain::{
    bake_terrain, bake_terrain_from, bake_terrain_streamed, bake_terrain_window, streams_angles,
    AngleBands, TerrainProducts, WindowPlace,
};

mod surface;
use surface::SurfaceTap;
pub use surface::{bake_surface, bake_surface_as, Surface, SurfaceJob, SurfaceMaps, SurfaceValues};
