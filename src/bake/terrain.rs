//! The terrain products' bakes (SPEC §3.7): [`bake_terrain`] of a whole map and
//! [`bake_terrain_window`] of a tile's interior (§7.1), which give the same values per texel.
//!
//! Both take `angles` and the SVF from the kernel's bins, either band by band from a kernel
//! with every bin of a row ([`Horizons::Rows`]) or azimuth by azimuth from `sweep`'s planes
//! ([`Horizons::Planes`], no far-field table), and leave every product that casts rays of its
//! own (true-north angles, distance, openness, the sun) to [`super::rays::RaySet::cast`]. They
//! live apart from the horizon-map bakes of `bake.rs` because they share nothing with them but
//! the kernels.

use super::*;

/// The terrain products of one bake (SPEC §3.7), band-major f32 planes of `width × height`;
/// hole texels hold `nodata` (NaN when none was declared).
#[derive(Debug, Clone)]
pub struct TerrainProducts {
    pub width: usize,
    pub height: usize,
    /// `bins` planes: band n is the horizon at n·360°/bins (`azimuth_from`), in `angle_unit`.
    pub angles: Option<Vec<f32>>,
    pub bins: usize,
    /// One plane.
    pub svf: Option<Vec<f32>>,
    /// `bins` planes in the bands' order, as `angles`: the distance (map units: `cell_size`,
    /// else texels) to the point that sets each horizon; `nodata` where the horizon is 0.
    pub distance: Option<Vec<f32>>,
    /// Positive and negative openness in degrees, one plane each.
    pub openness: Option<[Vec<f32>; 2]>,
    /// Hours of direct sun, and the clear-sky direct beam on the surface in Wh/m², over the
    /// days asked; one plane each.
    pub sun_hours: Option<Vec<f32>>,
    pub insolation: Option<Vec<f32>>,
    /// Where north is (SPEC §3.7 "True and grid north"), for bake.json.
    pub north: Option<crate::heightmap::north::NorthReport>,
    /// The value written at holes.
    pub nodata: f32,
}

/// Largest `angles` output held in memory, in values (W·H·bins): 1 GiB of f32.
pub const MAX_ANGLE_VALUES: u64 = 1 << 28;

/// Bakes the terrain products `params.outputs` asks for (`angles`, `svf`) from the per-bin
/// horizons of the bake's method at its radius, bins, edge and curvature: the kernels' bins
/// before any channel reduction ([`crate::terrain`] turns them into products).
///
/// # Errors
/// [`crate::Error::Canceled`]; [`crate::Error::Param`] when `angles` would not fit
/// ([`MAX_ANGLE_VALUES`]) or the method cannot give the bins asked.
pub fn bake_terrain(
    map: &HeightMap,
    params: &BakeParams,
    progress: &Progress,
) -> Result<(TerrainProducts, ResolvedRadius)> {
    check_angles(map, params)?;
    bake_terrain_from(map, map.scaled(params.height_scale), params, progress)
}

/// [`bake_terrain`] from the map's heights already scaled: `heights` is
/// `map.scaled(params.height_scale)`, bit for bit. A caller done with the map's values hands
/// them over scaled in place ([`HeightMap::take_scaled`]), so the bake holds one copy of the
/// map rather than two (an 8192² DEM: 256 MiB). `map.values` is read again only for the sun
/// products' heights in metres, so with `sun_hours` or `insolation` it must still hold them.
///
/// # Errors
/// As [`bake_terrain`]; [`crate::Error::Internal`] when `heights` is not the map's size, or
/// the sun products are asked of a map whose values were taken.
pub fn bake_terrain_from(
    map: &HeightMap,
    heights: Vec<f32>,
    params: &BakeParams,
    progress: &Progress,
) -> Result<(TerrainProducts, ResolvedRadius)> {
    terrain_core(map, heights, params, progress, None)
}

/// Where [`bake_terrain_streamed`] hands the `angles`: each output band once, whole (its row y
/// is `row(y)`: the map's width of values in `angle_unit`, holes at the nodata value), in the
/// order the bins are swept.
pub type AngleBands<'a> = &'a mut (dyn for<'p> FnMut(usize, &(dyn Fn(usize) -> &'p [f32] + Sync + 'p)) -> Result<()>
             + 'a);

/// Whether [`bake_terrain_streamed`] hands the `angles` on band by band ([`AngleBands`]) rather
/// than in its products: `sweep`'s planes, unless the bands are true-north azimuths turned per
/// texel (their own rays).
pub fn streams_angles(map: &HeightMap, params: &BakeParams) -> bool {
    streams(params, &compass_of(map, params).0)
}

fn streams(params: &BakeParams, compass: &crate::heightmap::north::Compass) -> bool {
    params.outputs.angles && azimuth_major(params) && !true_bands(params, compass)
}

/// Compass bands on a projected map are true azimuths, turned per texel: rays of their own.
fn true_bands(params: &BakeParams, compass: &crate::heightmap::north::Compass) -> bool {
    params.azimuth_from == AzimuthFrom::NorthCw && compass.is_true()
}

/// [`bake_terrain_from`], with the `angles` handed to `angles` band by band as they are made
/// where [`streams_angles`] says so (the products then hold none): one plane per bin in
/// flight, not W·H·bins, so any bins fit at any size ([`MAX_ANGLE_VALUES`] holds only where
/// they are not streamed).
///
/// # Errors
/// As [`bake_terrain_from`], and what `angles` fails with.
pub fn bake_terrain_streamed(
    map: &HeightMap,
    heights: Vec<f32>,
    params: &BakeParams,
    progress: &Progress,
    angles: AngleBands<'_>,
) -> Result<(TerrainProducts, ResolvedRadius)> {
    terrain_core(map, heights, params, progress, Some(angles))
}

fn terrain_core(
    map: &HeightMap,
    heights: Vec<f32>,
    params: &BakeParams,
    progress: &Progress,
    out: Option<AngleBands<'_>>,
) -> Result<(TerrainProducts, ResolvedRadius)> {
    let (w, h) = (map.width, map.height);
    let nb = params.bins as usize;
    let (compass, north) = compass_of(map, params);
    let out = out.filter(|_| streams(params, &compass));
    if out.is_none() {
        check_angles(map, params)?;
    }
    let values = if params.outputs.sun() { map.values.len() } else { w * h };
    if heights.len() != w * h || values != w * h {
        return Err(crate::Error::Internal(format!(
            "a {w}×{h} terrain bake was given {} heights and {} values",
            heights.len(),
            map.values.len()
        )));
    }
    check_scaled(&heights)?;
    let radius = resolve_radius(params, w, h, &heights);
    let grid = Grid::new(w, h, &heights, params.edge, params.y_axis);
    let holes = map.terrain.holes.as_deref();
    // `sweep` gives its horizons plane by plane where the products only fold over bins: no
    // far-field table (W·H·bins) in memory or on disk.
    let (rows_kernel, planes_kernel);
    let kernel: Horizons<'_> = if azimuth_major(params) {
        planes_kernel = sweep_kernel(params, grid, radius.texels, progress, holes, true);
        Horizons::Planes(&planes_kernel)
    } else {
        rows_kernel = make_kernel_for(params, grid, radius.texels, progress, holes);
        Horizons::Rows(rows_kernel.as_ref())
    };
    if kernel.bins() != nb {
        return Err(crate::Error::param(
            "bins",
            format!("method={:?} computes at least {} bins", params.method, kernel.bins())
                .to_lowercase(),
        ));
    }
    let nodata = map.terrain.nodata.map_or(f32::NAN, |v| v as f32);
    let normals = NormalSource { grid: &grid, holes, row0: 0 };
    let true_bands = true_bands(params, &compass);
    let mut kernel_params = params.clone();
    kernel_params.outputs.angles &= !true_bands;
    let (mut ang, sv) = if kernel_params.outputs.angles || params.outputs.svf {
        terrain_planes(kernel, &kernel_params, holes, nodata, &normals, progress, out)?
    } else {
        (None, None)
    };
    let metres = || map.values.iter().map(|v| (f64::from(*v) * params.linear_unit_m) as f32);
    let rays = rays::RaySet { grid, compass: &compass, true_bands, holes, nodata };
    let (true_ang, more) =
        rays.cast(params, radius.texels, 0..h, metres, centre_lat_lon(map), progress)?;
    ang = true_ang.or(ang);
    let rays::RayProducts { distance, openness, sun_hours, insolation } = more;
    let products = TerrainProducts {
        width: w,
        height: h,
        angles: ang,
        bins: nb,
        svf: sv,
        distance,
        openness,
        sun_hours,
        insolation,
        north: map.terrain.georef.is_some().then_some(north),
        nodata,
    };
    Ok((products, radius))
}

/// Refuses `angles` that would not fit ([`MAX_ANGLE_VALUES`]), before anything is made.
fn check_angles(map: &HeightMap, params: &BakeParams) -> Result<()> {
    let (w, h, nb) = (map.width, map.height, params.bins as usize);
    if params.outputs.angles && (w * h) as u64 * nb as u64 > MAX_ANGLE_VALUES {
        return Err(crate::Error::param(
            "bins",
            format!(
                "angles of a {w}×{h} map at {nb} bins are {} values, above the limit of \
                 {MAX_ANGLE_VALUES}; use fewer bins or a smaller map",
                (w * h) as u64 * nb as u64
            ),
        ));
    }
    Ok(())
}

/// Where a window lies in the map its georeferencing describes: its first texel and the map's
/// size (true north and the sun's place are the whole map's, SPEC §3.7, §7.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WindowPlace {
    pub origin: (usize, usize),
    pub map: (usize, usize),
}

/// `angles` (band-major) and `svf` planes, each when asked.
type TerrainPlanes = (Option<Vec<f32>>, Option<Vec<f32>>);

/// The terrain planes (`angles`, `svf`, as `params.outputs` asks) of every row of `kernel`,
/// band-major f32 planes of its width × height; `holes` (one per texel of those rows) get
/// `nodata`. What [`bake_terrain`] and [`bake_terrain_window`] share.
///
/// # Errors
/// [`crate::Error::Canceled`].
/// The heights a texel's normal comes from (`svf_model=tilted`): the grid, its holes (every
/// texel of the grid), and the grid row of the kernel's row 0 (a tile's window starts its
/// kernel rows at the interior; its columns are the grid's).
struct NormalSource<'a> {
    grid: &'a Grid<'a>,
    holes: Option<&'a [bool]>,
    row0: usize,
}

fn terrain_planes(
    kernel: Horizons<'_>,
    params: &BakeParams,
    holes: Option<&[bool]>,
    nodata: f32,
    normals: &NormalSource<'_>,
    progress: &Progress,
    out: Option<AngleBands<'_>>,
) -> Result<TerrainPlanes> {
    use crate::terrain::{angles, surface, svf};
    let kernel = match kernel {
        Horizons::Rows(k) => k,
        Horizons::Planes(k) => return folded_planes(k, params, holes, nodata, progress, out),
    };
    let tilted = params.svf_model == crate::params::SvfModel::Tilted;
    let dirs = surface::BinDirs::new(params.bins as usize);
    let (w, h, nb) = (kernel.width(), kernel.height(), params.bins as usize);
    let order = angles::band_bins(nb, params.azimuth_from, params.y_axis);
    let plane = w * h;
    let mut ang = params.outputs.angles.then(|| vec![0f32; plane * nb]);
    let mut sv = params.outputs.svf.then(|| vec![0f32; plane]);
    let band = kernels::band_rows_for(kernel);
    progress.start(Stage::Bake, h as u64);
    {
        // Planes are written band by band: each kernel band owns the same rows of every plane.
        let ang_rows: Option<Vec<Vec<Mutex<&mut [f32]>>>> =
            ang.as_mut().map(|a| a.chunks_mut(plane).map(|p| split(p, band * w)).collect());
        let sv_rows = sv.as_mut().map(|s| split(s, band * w));
        kernels::run_bands(kernel, band, true, progress, |bi, b: Band<'_>| {
            let Some(bins) = b.bins else { return };
            let mut planes: Vec<_> = match &ang_rows {
                Some(a) => a.iter().filter_map(|p| p[bi].lock().ok()).collect(),
                None => Vec::new(),
            };
            let mut svf_rows = sv_rows.as_ref().and_then(|s| s[bi].lock().ok());
            for (t, s) in bins.chunks_exact(nb).enumerate() {
                let hole = holes.is_some_and(|m| m[b.y0 * w + t]);
                if !planes.is_empty() {
                    if hole {
                        planes.iter_mut().for_each(|p| p[t] = nodata);
                    } else {
                        angles::texel_angles(s, &order, params.angle_unit, |band, v| {
                            planes[band][t] = v
                        });
                    }
                }
                if let Some(out) = svf_rows.as_mut() {
                    out[t] = if hole {
                        nodata
                    } else if tilted {
                        let (x, y) = (t % w, normals.row0 + b.y0 + t / w);
                        let n = surface::normal(normals.grid, normals.holes, x, y);
                        svf::svf_tilted(s, n, &dirs)
                    } else {
                        svf::svf(s, params.svf_model)
                    };
                }
            }
        })?;
    }
    Ok((ang, sv))
}

/// Where the terrain planes' horizons come from: a kernel's bands, or `sweep`'s planes.
#[derive(Clone, Copy)]
enum Horizons<'k> {
    Rows(&'k dyn HorizonRows),
    Planes(&'k kernels::sweep::Sweep<'k>),
}

impl Horizons<'_> {
    fn bins(&self) -> usize {
        match self {
            Horizons::Rows(k) => k.bins(),
            Horizons::Planes(k) => k.bins(),
        }
    }
}

/// Whether [`bake_terrain`]'s `angles` and `svf` come from `sweep`'s planes
/// ([`folded_planes`]): `sweep`, and an SVF (if any) that is a plain sum over bins (`tilted`
/// takes every bin of a texel at once, with its normal).
pub(super) fn azimuth_major(params: &BakeParams) -> bool {
    params.method == Method::Sweep
        && !(params.outputs.svf && params.svf_model == crate::params::SvfModel::Tilted)
}

/// [`terrain_planes`] from `sweep`'s planes, bin after bin ([`kernels::sweep::Sweep::planes`]):
/// each bin's plane goes to its `angles` band, and the SVF's sum over bins is kept per texel
/// in f32 and added to in the bins' order, as [`crate::terrain::svf::svf`] adds, so the values
/// are those of the bands bit for bit with a memory of one plane per azimuth in flight.
fn folded_planes(
    kernel: &kernels::sweep::Sweep<'_>,
    params: &BakeParams,
    holes: Option<&[bool]>,
    nodata: f32,
    progress: &Progress,
    mut out: Option<AngleBands<'_>>,
) -> Result<TerrainPlanes> {
    use crate::terrain::{angles, svf};
    let (w, h, nb) = (kernel.width(), kernel.height(), params.bins as usize);
    let plane = w * h;
    // Output band of each bin (`band_bins` gives the bin of each band).
    let mut band_of = vec![0usize; nb];
    for (band, &bin) in angles::band_bins(nb, params.azimuth_from, params.y_axis).iter().enumerate()
    {
        band_of[bin] = band;
    }
    // Streamed, the angles of the bins in flight only (bin n in plane n mod k: a chunk of
    // bins is k consecutive ones), each handed on whole once its last band is in; else all.
    let streamed = params.outputs.angles && out.is_some();
    let in_flight = if streamed { kernel.planes_in_flight() } else { nb };
    let mut ang = params.outputs.angles.then(|| vec![0f32; plane * in_flight]);
    let mut sums = params.outputs.svf.then(|| vec![0f32; plane]);
    let band = kernels::band_rows_for(kernel);
    progress.start(Stage::Bake, (h * nb) as u64);
    {
        let ang_rows: Option<Vec<Vec<Mutex<&mut [f32]>>>> =
            ang.as_mut().map(|a| a.chunks_mut(plane).map(|p| split(p, band * w)).collect());
        let sum_rows = sums.as_mut().map(|s| split(s, band * w));
        let slot = |n: usize| if streamed { n % in_flight } else { band_of[n] };
        let done = |bins: &[usize]| -> Result<()> {
            let (Some(put), Some(a)) = (out.as_mut(), ang_rows.as_ref()) else { return Ok(()) };
            for &n in bins {
                let mut rows: Vec<_> = a[slot(n)]
                    .iter()
                    .map(|m| m.lock().unwrap_or_else(|e| e.into_inner()))
                    .collect();
                if let Some(m) = holes {
                    for (b, r) in rows.iter_mut().enumerate() {
                        let m = &m[b * band * w..][..r.len()];
                        r.iter_mut()
                            .zip(m)
                            .filter(|(_, &hole)| hole)
                            .for_each(|(o, _)| *o = nodata);
                    }
                }
                put(band_of[n], &rows_of(&rows, band, w))?;
            }
            Ok(())
        };
        kernel.planes_then(
            band,
            progress,
            |b, n, s| {
                if let Some(a) = &ang_rows {
                    if let Ok(mut p) = a[slot(n)][b].lock() {
                        for (o, &v) in p.iter_mut().zip(s) {
                            *o = angles::angle(v, params.angle_unit);
                        }
                    }
                }
                if let Some(mut acc) = sum_rows.as_ref().and_then(|r| r[b].lock().ok()) {
                    // The terms of `svf::svf`, in its order.
                    for (a, &v) in acc.iter_mut().zip(s) {
                        *a += svf::blocked(v, params.svf_model);
                    }
                }
            },
            done,
        )?;
    }
    if streamed {
        ang = None;
    }
    let sv = sums.map(|sums| {
        let mut out: Vec<f32> = sums.iter().map(|&s| svf::from_blocked(s, nb)).collect();
        if let Some(m) = holes {
            out.iter_mut().zip(m).filter(|(_, &hole)| hole).for_each(|(o, _)| *o = nodata);
        }
        out
    });
    if let (Some(a), Some(m)) = (ang.as_mut(), holes) {
        for p in a.chunks_exact_mut(plane) {
            p.iter_mut().zip(m).filter(|(_, &hole)| hole).for_each(|(o, _)| *o = nodata);
        }
    }
    Ok((ang, sv))
}

/// Row y of a plane held as bands of `band` rows of `w` values.
fn rows_of<'r, 's: 'r, R: std::ops::Deref<Target = &'s mut [f32]> + Sync>(
    bands: &'r [R],
    band: usize,
    w: usize,
) -> impl Fn(usize) -> &'r [f32] + Sync + 'r {
    move |y| &bands[y / band][(y % band) * w..][..w]
}

/// The terrain products (`angles`, `svf`) of the interior of one tile of a tiled bake (SPEC
/// §7.1), as [`bake_window`] bakes its horizon layers: `window` is the tile's window of the map
/// (unscaled values, holes, the map's nodata), `interior` = (column, row, width, height) inside
/// it, `range` the whole map's scaled height range and `radius` the radius resolved on the whole
/// map. Per texel the same values as [`bake_terrain`] of the whole map.
///
/// # Errors
/// [`crate::Error::Canceled`]; [`crate::Error::Param`] when the method cannot give the bins
/// asked.
pub fn bake_terrain_window(
    window: HeightMap,
    params: &BakeParams,
    interior: (usize, usize, usize, usize),
    place: Option<WindowPlace>,
    range: (f32, f32),
    radius: u32,
    progress: &Progress,
) -> Result<TerrainProducts> {
    let (ww, wh) = (window.width, window.height);
    let (ox, oy, iw, ih) = interior;
    assert!(ox + iw <= ww && oy + ih <= wh, "interior outside its window");
    let nb = params.bins as usize;
    let mut window = window;
    let holes = window.terrain.holes.take();
    let nodata = window.terrain.nodata.map_or(f32::NAN, |v| v as f32);
    let georef = window.terrain.georef.take();
    let (origin, map_size) = place.map_or(((0, 0), (ww, wh)), |p| (p.origin, p.map));
    let (compass, north) = crate::heightmap::north::compass(
        georef.as_ref(),
        origin,
        (ww, wh),
        map_size,
        params.y_axis,
    );
    let true_bands = (params.outputs.angles || params.outputs.horizon_distance)
        && params.azimuth_from == AzimuthFrom::NorthCw
        && compass.is_true();
    if true_bands && place.is_none() {
        return Err(crate::Error::param(
            "azimuth_from",
            "north_cw bands are true azimuths, turned per texel by the map's projection, and a \
             block that does not know where it lies in the map cannot turn them: use east_ccw \
             (grid azimuths), or bake the whole map",
        ));
    }
    let metres: Vec<f32> = if params.outputs.sun() {
        window.values.iter().map(|v| (f64::from(*v) * params.linear_unit_m) as f32).collect()
    } else {
        Vec::new()
    };
    let heights = window.into_scaled(params.height_scale);
    let grid = Grid::new(ww, wh, &heights, params.edge, params.y_axis).with_range(range.0, range.1);
    let kernel = make_kernel_for(params, grid, radius, progress, holes.as_deref());
    if kernel.bins() != nb {
        return Err(crate::Error::param(
            "bins",
            format!("method={:?} computes at least {} bins", params.method, kernel.bins())
                .to_lowercase(),
        ));
    }
    let rows = RowWindow { inner: kernel, oy, rows: ih };
    let row_holes = holes.as_deref().map(|m| &m[oy * ww..(oy + ih) * ww]);
    let normals = NormalSource { grid: &grid, holes: holes.as_deref(), row0: oy };
    let mut kernel_params = params.clone();
    kernel_params.outputs.angles &= !true_bands;
    let (mut ang, sv) = if kernel_params.outputs.angles || params.outputs.svf {
        terrain_planes(
            Horizons::Rows(&rows),
            &kernel_params,
            row_holes,
            nodata,
            &normals,
            progress,
            None,
        )?
    } else {
        (None, None)
    };
    let rays =
        rays::RaySet { grid, compass: &compass, true_bands, holes: holes.as_deref(), nodata };
    let centre = rays::centre_of(georef.as_ref(), map_size);
    let rows = oy..oy + ih;
    let (true_ang, more) =
        rays.cast(params, radius, rows, || metres.iter().copied(), centre, progress)?;
    ang = true_ang.or(ang);
    // Keep the interior's columns, plane by plane, in place (each row moves to the left).
    let cut = |mut v: Vec<f32>| {
        let planes = v.len() / (ww * ih);
        for k in 0..planes * ih {
            let from = k * ww + ox;
            v.copy_within(from..from + iw, k * iw);
        }
        v.truncate(planes * ih * iw);
        v.shrink_to_fit();
        v
    };
    Ok(TerrainProducts {
        width: iw,
        height: ih,
        angles: ang.map(cut),
        bins: nb,
        svf: sv.map(cut),
        distance: more.distance.map(cut),
        openness: more.openness.map(|[p, n]| [cut(p), cut(n)]),
        sun_hours: more.sun_hours.map(cut),
        insolation: more.insolation.map(cut),
        north: georef.is_some().then_some(north),
        nodata,
    })
}
