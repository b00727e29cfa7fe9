//! The products of one exact ray per texel and azimuth (SPEC §3.7): openness, horizon
//! distance, the sun's shadow, sun hours and insolation, the horizon profile, and compass bands
//! on a projected map. What they share, and why they are not the kernels' bins: each asks for
//! an azimuth per texel (the sun's, or a true azimuth turned by the meridian convergence
//! there, [`crate::heightmap::north`]) or for something a bin keeps no trace of (the point that
//! sets the horizon, a signed elevation), so each walks `exact`'s ray itself, whatever the
//! bake's method, row by row on the rayon pool with cancellation between rows.

use super::{bake_horizon, check_scaled, curvature, resolve_radius};
use crate::error::Result;
use crate::heightmap::north::{self, Compass, NorthReport};
use crate::heightmap::HeightMap;
use crate::kernels::{self, Grid, HorizonRows};
use crate::params::{AzimuthFrom, BakeParams, Method, Radius};
use crate::progress::{Progress, Stage};
use crate::terrain::sun::SunAzimuth;

/// Positive and negative openness (SPEC §3.7, Yokoyama et al. 2002, as RVT computes them), in
/// degrees: the mean over the `bins` azimuths of 90° − β_n, β_n the signed maximum elevation
/// angle within `radius` texels (no clamp at 0), on the surface and on the inverted surface −h;
/// by the cell walk over the bilinear surface ([`kernels::exact::SignedElevations`]: the
/// plain walk's values, sooner),
/// without the earth-curvature drop (as RVT), holes no surface; an azimuth whose ray meets no
/// surface (no length at an `edge=none` border, or holes only) is left out of the mean.
/// `nodata` at holes.
///
/// # Errors
/// [`crate::Error::Canceled`].
fn openness_planes(
    grid: Grid<'_>,
    params: &BakeParams,
    radius: u32,
    rows: std::ops::Range<usize>,
    holes: Option<&[bool]>,
    nodata: f32,
    progress: &Progress,
) -> Result<[Vec<f32>; 2]> {
    use rayon::prelude::*;
    let (w, h) = (grid.width, rows.len());
    // The inverted surface's holes filled far below it again (−h would put them far above,
    // and the walks' pyramid would then skip nothing near them).
    let mut inverted: Vec<f32> = grid.heights.iter().map(|v| -v).collect();
    if let Some(m) = holes {
        let surface = inverted.iter().zip(m).filter(|(_, &o)| !o).map(|(&v, _)| v);
        let (lo, hi) = surface.fold((f32::MAX, f32::MIN), |(a, b), v| (a.min(v), b.max(v)));
        let fill = crate::heightmap::hole_fill(lo, hi.max(lo));
        for (v, _) in inverted.iter_mut().zip(m).filter(|(_, &o)| o) {
            *v = fill;
        }
    }
    let grids = [grid, Grid::new(w, grid.height, &inverted, params.edge, params.y_axis)];
    let nb = params.bins as usize;
    let phis: Vec<f64> = (0..nb).map(|n| n as f64 * std::f64::consts::TAU / nb as f64).collect();
    let r = f64::from(radius);
    let mut planes = [vec![nodata; w * h], vec![nodata; w * h]];
    progress.start(Stage::Bake, 2 * h as u64);
    for (g, plane) in grids.iter().zip(planes.iter_mut()) {
        let walks = kernels::exact::SignedElevations::new(*g, holes, r);
        plane.par_chunks_mut(w).enumerate().try_for_each(|(j, row)| {
            if progress.is_canceled() {
                return Err(crate::Error::Canceled);
            }
            let y = rows.start + j;
            for (x, o) in row.iter_mut().enumerate() {
                if holes.is_some_and(|m| m[y * w + x]) {
                    continue;
                }
                let (mut sum, mut n) = (0.0f64, 0usize);
                for &phi in &phis {
                    if let Some(beta) = walks.at(x, y, phi) {
                        sum += 90.0 - beta.to_degrees();
                        n += 1;
                    }
                }
                if n > 0 {
                    *o = (sum / n as f64) as f32;
                }
            }
            progress.advance(1);
            Ok(())
        })?;
    }
    Ok(planes)
}

/// `horizon_distance` (SPEC §3.7): for every texel and bin, the distance along the ray to the
/// point that sets the horizon, by one exact walk per bin whatever the bake's method (the ray
/// methods other than `exact` keep no such point), with its radius, curvature and holes; in map
/// units (`cell_size`, else texels), `nodata` at holes and where the horizon is 0. Band-major in
/// the order of `angles.tif`'s bands.
///
/// # Errors
/// [`crate::Error::Canceled`].
#[allow(clippy::too_many_arguments)]
fn horizon_distances(
    k: &kernels::exact::ExactHorizon<'_>,
    params: &BakeParams,
    true_bands: Option<&Compass>,
    rows: std::ops::Range<usize>,
    holes: Option<&[bool]>,
    nodata: f32,
    progress: &Progress,
) -> Result<Vec<f32>> {
    let nb = params.bins as usize;
    let order = crate::terrain::angles::band_bins(nb, params.azimuth_from, params.y_axis);
    let unit = params.cell_size.unwrap_or(1.0);
    per_texel_bands(k.width(), rows, nb, holes, nodata, progress, |x, y, bands| {
        for (band, o) in bands.iter_mut().enumerate() {
            let (t, s) = match true_bands {
                // Compass bands on a projected map: the true azimuth's φ at this texel.
                Some(c) => k.horizon_and_distance_at(
                    x,
                    y,
                    c.phi(x, y, crate::terrain::angles::band_azimuth_deg(band, nb)),
                ),
                None => k.horizon_and_distance(x, y, order[band]),
            };
            if t > 0.0 {
                *o = (s * unit) as f32;
            }
        }
    })
}

/// Band-major planes of `nb` values per texel of `rows` (every column of a `w`-wide grid), a
/// texel's bands set by `texel(x, y, bands)` (holes keep `nodata`), row by row on the pool with
/// cancellation between rows; texel-major while computed, then transposed.
///
/// # Errors
/// [`crate::Error::Canceled`].
fn per_texel_bands(
    w: usize,
    rows: std::ops::Range<usize>,
    nb: usize,
    holes: Option<&[bool]>,
    nodata: f32,
    progress: &Progress,
    texel: impl Fn(usize, usize, &mut [f32]) + Sync,
) -> Result<Vec<f32>> {
    use rayon::prelude::*;
    let h = rows.len();
    let mut texels = vec![nodata; w * h * nb];
    progress.start(Stage::Bake, h as u64);
    texels.par_chunks_mut(w * nb).enumerate().try_for_each(|(j, row)| {
        if progress.is_canceled() {
            return Err(crate::Error::Canceled);
        }
        let y = rows.start + j;
        for (x, bands) in row.chunks_exact_mut(nb).enumerate() {
            if !holes.is_some_and(|m| m[y * w + x]) {
                texel(x, y, bands);
            }
        }
        progress.advance(1);
        Ok(())
    })?;
    Ok(transpose_bands(&texels, nb))
}

/// The per-texel ray products of one map or window, each when `params.outputs` asks.
#[derive(Default)]
pub struct RayProducts {
    pub distance: Option<Vec<f32>>,
    pub openness: Option<[Vec<f32>; 2]>,
    pub sun_hours: Option<Vec<f32>>,
    pub insolation: Option<Vec<f32>>,
}

/// What the rays of a map or a tile's window share: its grid, the compass over it, whether
/// compass bands are true azimuths, holes and nodata.
pub struct RaySet<'a> {
    pub grid: Grid<'a>,
    pub compass: &'a Compass,
    pub true_bands: bool,
    pub holes: Option<&'a [bool]>,
    pub nodata: f32,
}

impl RaySet<'_> {
    /// The rays a terrain bake casts of its own, of the grid's `rows` (every column): `angles`
    /// in true compass bands (when `true_bands` and asked; band-major, `None` otherwise) and
    /// the [`RayProducts`]. The exact ray kernel ([`ray_kernel`]) is built only when one of
    /// them is asked ([`needs_rays`]). The one place [`super::bake_terrain`] and
    /// [`super::bake_terrain_window`] cast rays, so the two cannot differ.
    ///
    /// # Errors
    /// As [`RaySet::products`].
    pub fn cast<I: Iterator<Item = f32>>(
        &self,
        params: &BakeParams,
        radius: u32,
        rows: std::ops::Range<usize>,
        metres: impl FnOnce() -> I,
        centre: Option<(f64, f64)>,
        progress: &Progress,
    ) -> Result<(Option<Vec<f32>>, RayProducts)> {
        if !needs_rays(params, self.true_bands) {
            return Ok((None, RayProducts::default()));
        }
        let k = ray_kernel(self.grid, params, radius, self.holes);
        let angles = match params.outputs.angles && self.true_bands {
            true => Some(true_north_angles(
                &k,
                params,
                self.compass,
                rows.clone(),
                self.holes,
                self.nodata,
                progress,
            )?),
            false => None,
        };
        let more = self.products(&k, params, radius, rows, metres, centre, progress)?;
        Ok((angles, more))
    }

    /// `horizon_distance`, `openness`, `sun_hours` and `insolation` of the grid's `rows` (every
    /// column) by the ray kernel `kernel`, as `params.outputs` asks; `metres` gives the
    /// heights in metres (for the air pressure), `centre` the map's centre (the sun's default
    /// place).
    ///
    /// # Errors
    /// [`crate::Error::Canceled`] and the products' refusals.
    #[allow(clippy::too_many_arguments)] // the kernel, the rows and what the sun needs
    fn products<I: Iterator<Item = f32>>(
        &self,
        kernel: &kernels::exact::ExactHorizon<'_>,
        params: &BakeParams,
        radius: u32,
        rows: std::ops::Range<usize>,
        metres: impl FnOnce() -> I,
        centre: Option<(f64, f64)>,
        progress: &Progress,
    ) -> Result<RayProducts> {
        let o = params.outputs;
        let (holes, nodata) = (self.holes, self.nodata);
        let bands = self.true_bands.then_some(self.compass);
        let distance = match o.horizon_distance {
            true => Some(horizon_distances(
                kernel,
                params,
                bands,
                rows.clone(),
                holes,
                nodata,
                progress,
            )?),
            false => None,
        };
        let openness = match o.openness {
            true => Some(openness_planes(
                self.grid,
                params,
                radius,
                rows.clone(),
                holes,
                nodata,
                progress,
            )?),
            false => None,
        };
        let [sun_hours, insolation] = if o.sun() {
            let (suns, step_hours) = sun_steps(params, centre)?;
            let metres: Vec<f32> = metres().collect();
            sun_planes(
                kernel,
                &self.grid,
                params,
                self.compass,
                &suns,
                step_hours,
                &metres,
                rows,
                holes,
                nodata,
                progress,
            )?
        } else {
            [None, None]
        };
        Ok(RayProducts { distance, openness, sun_hours, insolation })
    }
}

/// The exact horizon profile (SPEC §3.7) of texel (`x`, `y`): (azimuth, elevation) in degrees
/// at `bins` azimuths counted as `params.azimuth_from` says, with the bake's radius, edge and
/// earth curvature (always `method=exact`: one ray per azimuth).
///
/// # Errors
/// [`crate::Error::Param`] naming `at` for a texel outside the map or on a hole.
pub fn horizon_profile(
    map: &HeightMap,
    params: &BakeParams,
    x: usize,
    y: usize,
    bins: usize,
) -> Result<Vec<(f64, f64)>> {
    if x >= map.width || y >= map.height {
        return Err(crate::Error::param(
            "at",
            format!("texel ({x}, {y}) is outside the {}×{} map", map.width, map.height),
        ));
    }
    if map.terrain.holes.as_ref().is_some_and(|h| h[y * map.width + x]) {
        return Err(crate::Error::param("at", format!("texel ({x}, {y}) is nodata (a hole)")));
    }
    let heights = map.scaled(params.height_scale);
    check_scaled(&heights)?;
    let radius = resolve_radius(params, map.width, map.height, &heights);
    let grid = Grid::new(map.width, map.height, &heights, params.edge, params.y_axis);
    let r = (params.radius != Radius::Unlimited || params.max_distance.is_some())
        .then_some(radius.texels);
    let k = kernels::exact::ExactHorizon::new(grid, r, 16, crate::params::Reduce::Point)
        .with_curvature(curvature(params))
        .with_holes(map.terrain.holes.as_deref());
    let (compass, _) = compass_of(map, params);
    let to_phi = |az: f64| match params.azimuth_from {
        AzimuthFrom::NorthCw => compass.phi(x, y, az),
        AzimuthFrom::EastCcw => az.rem_euclid(360.0).to_radians(),
    };
    Ok(crate::terrain::profile::profile_with(bins, to_phi, |phi| k.horizon_sin(x, y, phi)))
}

/// The compass of a whole map (SPEC §3.7 "True and grid north"): compass azimuths through its
/// projection per texel, or on the grid, and what bake.json says of it.
pub fn compass_of(map: &HeightMap, params: &BakeParams) -> (Compass, NorthReport) {
    let size = (map.width, map.height);
    north::compass(map.terrain.georef.as_ref(), (0, 0), size, size, params.y_axis)
}

/// The latitude and longitude (degrees) of a DEM's centre, where its projection places it.
pub fn centre_lat_lon(map: &HeightMap) -> Option<(f64, f64)> {
    centre_of(map.terrain.georef.as_ref(), (map.width, map.height))
}

/// [`centre_lat_lon`] of a `size` map georeferenced by `georef`.
pub fn centre_of(
    georef: Option<&crate::heightmap::georef::Georef>,
    size: (usize, usize),
) -> Option<(f64, f64)> {
    let g = georef.filter(|g| g.is_dem())?;
    let geo = north::Geodesy::of(g).ok()?;
    let (lon, lat) = geo.lon_lat(size.0 as f64 / 2.0, size.1 as f64 / 2.0)?;
    Some((lat, lon))
}

/// The sun positions of `params`' days (SPEC §3.7 `sun_hours`, `insolation`) at its
/// `latitude`/`longitude`, else `centre`, and the hours each step stands for.
///
/// # Errors
/// [`crate::Error::Param`] naming `latitude` (no place) or `date`.
pub(super) fn sun_steps(
    params: &BakeParams,
    centre: Option<(f64, f64)>,
) -> Result<(Vec<crate::terrain::sun::Sun>, f64)> {
    let place = match (params.latitude, params.longitude) {
        (Some(a), Some(o)) => (a, o),
        _ => centre.ok_or_else(|| {
            crate::Error::param(
                "latitude",
                "sun_hours and insolation need the sun's place: give latitude and longitude, \
                 or a DEM whose projection places its centre",
            )
        })?,
    };
    let step = params.time_step_minutes.unwrap_or(crate::params::DEFAULT_TIME_STEP_MINUTES);
    let (Some(from), Some(to)) = (params.date_from.as_deref(), params.date_to.as_deref()) else {
        return Err(crate::Error::param("date", "sun_hours and insolation need a date"));
    };
    let suns = crate::terrain::sun::day_steps(from, to, step, place.0, place.1)?;
    Ok((suns, f64::from(step) / 60.0))
}

/// Whether a terrain bake casts rays of its own ([`ray_kernel`]): `angles` in true compass
/// bands (`true_bands`), or any of the ray products. Otherwise the kernel is never built (its
/// padded copy of the map is a few bytes a texel, of a bake that would not read it).
fn needs_rays(params: &BakeParams, true_bands: bool) -> bool {
    let o = params.outputs;
    (o.angles && true_bands) || o.horizon_distance || o.openness || o.sun_hours || o.insolation
}

/// The exact kernel of the per-texel rays: the bake's radius (none at `unlimited`), curvature
/// and holes.
fn ray_kernel<'a>(
    grid: Grid<'a>,
    params: &BakeParams,
    radius: u32,
    holes: Option<&'a [bool]>,
) -> kernels::exact::ExactHorizon<'a> {
    let r = (params.radius != Radius::Unlimited || params.max_distance.is_some()).then_some(radius);
    kernels::exact::ExactHorizon::new(grid, r, params.bins.max(1), crate::params::Reduce::Point)
        .with_curvature(curvature(params))
        .with_holes(holes)
}

/// `angles` with `azimuth_from=north_cw` on a map whose projection gives true north (SPEC §3.7):
/// band n is the horizon at true azimuth n·360°/bins, whose φ differs from texel to texel by
/// the meridian convergence, so no kernel bin holds it: one exact ray per texel and band at
/// that φ (the profile's and the shadow's ray), in `angle_unit`; band-major like
/// [`super::bake_terrain`]'s planes, `nodata` at holes. Of a window's rows `rows` (a tile's
/// interior rows; every column), with `compass` over the window.
///
/// # Errors
/// [`crate::Error::Canceled`].
fn true_north_angles(
    k: &kernels::exact::ExactHorizon<'_>,
    params: &BakeParams,
    compass: &Compass,
    rows: std::ops::Range<usize>,
    holes: Option<&[bool]>,
    nodata: f32,
    progress: &Progress,
) -> Result<Vec<f32>> {
    let nb = params.bins as usize;
    per_texel_bands(k.width(), rows, nb, holes, nodata, progress, |x, y, bands| {
        for (n, o) in bands.iter_mut().enumerate() {
            let phi = compass.phi(x, y, crate::terrain::angles::band_azimuth_deg(n, nb));
            *o = crate::terrain::angles::angle(k.horizon_sin(x, y, phi) as f32, params.angle_unit);
        }
    })
}

/// Texel-major bands (each texel's `nb` values together) as band-major planes.
fn transpose_bands(texels: &[f32], nb: usize) -> Vec<f32> {
    let plane = texels.len() / nb.max(1);
    let mut planes = vec![0f32; texels.len()];
    for (t, bands) in texels.chunks_exact(nb).enumerate() {
        for (band, &v) in bands.iter().enumerate() {
            planes[band * plane + t] = v;
        }
    }
    planes
}

/// Most texel × sun-step rays one `sun_hours`/`insolation` bake may cast (SPEC §10: bounded
/// before it costs): 2³⁰, about 20 CPU-minutes of unlimited rays on a 1000² DEM.
pub const MAX_SUN_RAYS: u64 = 1 << 30;

/// `sun_hours` and `insolation` (SPEC §3.7): over the sun positions `suns` (each standing for
/// `step_hours`, the sun above 0°), a texel counts a step where the sun clears its exact
/// horizon at the sun's own azimuth (true, turned to φ by `compass` per texel); insolation adds
/// the clear-sky direct normal irradiance ([`crate::terrain::sun::clear_sky_dni`], at the air
/// pressure of the texel's altitude `metres`) times the cosine of incidence on the surface
/// (its normal from central differences of the scaled heights, [`crate::terrain::surface`])
/// for those steps, in Wh/m². Each plane when `params.outputs` asks, `nodata` at holes.
///
/// # Errors
/// [`crate::Error::Canceled`]; [`crate::Error::Param`] naming `time_step_minutes` above
/// [`MAX_SUN_RAYS`].
#[allow(clippy::too_many_arguments)]
fn sun_planes(
    k: &kernels::exact::ExactHorizon<'_>,
    grid: &Grid<'_>,
    params: &BakeParams,
    compass: &Compass,
    suns: &[crate::terrain::sun::Sun],
    step_hours: f64,
    metres: &[f32],
    rows: std::ops::Range<usize>,
    holes: Option<&[bool]>,
    nodata: f32,
    progress: &Progress,
) -> Result<[Option<Vec<f32>>; 2]> {
    use crate::terrain::{shadow::lit, sun::SunAzimuth};
    use rayon::prelude::*;
    let (w, h) = (grid.width, rows.len());
    let rows_of = |m: &[bool]| m[rows.start * w..rows.end * w].iter().filter(|&&b| !b).count();
    let valid = holes.map_or(w * h, rows_of);
    let rays = valid as u64 * suns.len() as u64;
    if rays > MAX_SUN_RAYS {
        return Err(crate::Error::param(
            "time_step_minutes",
            format!(
                "{valid} texels × {} sun positions are {rays} rays, above the limit of \
                 {MAX_SUN_RAYS}: take a longer time step, fewer days or a smaller map",
                suns.len()
            ),
        ));
    }
    let (want_hours, want_sun) = (params.outputs.sun_hours, params.outputs.insolation);
    let mut hours = vec![nodata; w * h];
    let mut energy = vec![nodata; w * h];
    progress.start(Stage::Bake, h as u64);
    hours.par_chunks_mut(w).zip(energy.par_chunks_mut(w)).enumerate().try_for_each(
        |(j, (hrow, erow))| {
            if progress.is_canceled() {
                return Err(crate::Error::Canceled);
            }
            let y = rows.start + j;
            for x in 0..w {
                if holes.is_some_and(|m| m[y * w + x]) {
                    continue;
                }
                let n = want_sun.then(|| crate::terrain::surface::normal(grid, holes, x, y));
                let pressure = crate::terrain::sun::pressure_at(f64::from(metres[y * w + x]));
                let (mut lit_steps, mut wh) = (0u32, 0.0f64);
                for sun in suns {
                    let phi = SunAzimuth::True(sun.azimuth_north_cw).phi(compass, x, y);
                    if !lit(k.horizon_sin(x, y, phi), sun.elevation) {
                        continue;
                    }
                    lit_steps += 1;
                    if let Some(n) = n {
                        let l = crate::terrain::shadow::sun_direction(phi, sun.elevation);
                        let cos_i = n[0] * l[0] + n[1] * l[1] + n[2] * l[2];
                        if cos_i > 0.0 {
                            let dni = crate::terrain::sun::clear_sky_dni(sun.elevation, pressure);
                            wh += dni * cos_i * step_hours;
                        }
                    }
                }
                hrow[x] = (f64::from(lit_steps) * step_hours) as f32;
                erow[x] = wh as f32;
            }
            progress.advance(1);
            Ok(())
        },
    )?;
    Ok([want_hours.then_some(hours), want_sun.then_some(energy)])
}

/// The sun shadow of every texel (SPEC §3.7): [`crate::terrain::shadow::LIT`] where the sun at
/// `azimuth_deg` (counted as `params.azimuth_from` says) and `elevation_deg` stands above the
/// exact horizon at its own azimuth, with the bake's radius, edge, curvature and holes (holes:
/// [`crate::terrain::shadow::NODATA`]). One exact ray per texel with the ray methods; with
/// `lengyel` (no ray), lit means L_z > s of §3.3 decoded from its baked 8-bit layers
/// ([`crate::terrain::shadow::lit_from_layers`]).
///
/// # Errors
/// [`crate::Error::Canceled`] when `progress` is canceled.
pub fn shadow(
    map: &HeightMap,
    params: &BakeParams,
    azimuth: SunAzimuth,
    elevation_deg: f64,
    progress: &Progress,
) -> Result<Vec<u8>> {
    use crate::terrain::shadow::{lit, LIT, NODATA, SHADOW};
    use rayon::prelude::*;
    let (w, h) = (map.width, map.height);
    let holes = map.terrain.holes.as_deref();
    let mut out = vec![SHADOW; w * h];
    if let Some(m) = holes {
        for (o, &hole) in out.iter_mut().zip(m) {
            if hole {
                *o = NODATA;
            }
        }
    }
    if elevation_deg <= 0.0 {
        return Ok(out);
    }
    let (compass, _) = compass_of(map, params);
    if params.method == Method::Lengyel {
        // One φ for the map (the layers are decoded for one light): the centre's.
        let phi = azimuth.phi(&compass, w / 2, h / 2);
        let (layers, _) = bake_horizon(map, params, crate::layers::Precisions::U8, progress)?;
        let [l0, l1] = layers
            .u8
            .as_ref()
            .ok_or_else(|| crate::Error::Internal("no 8-bit layers for the shadow".into()))?;
        crate::terrain::shadow::lit_from_layers(
            [l0, l1],
            params.encoding,
            phi,
            elevation_deg,
            &mut out,
        );
        return Ok(out);
    }
    let heights = map.scaled(params.height_scale);
    check_scaled(&heights)?;
    let radius = resolve_radius(params, w, h, &heights);
    let grid = Grid::new(w, h, &heights, params.edge, params.y_axis);
    let k = ray_kernel(grid, params, radius.texels, holes);
    progress.start(Stage::Bake, h as u64);
    out.par_chunks_mut(w).enumerate().try_for_each(|(y, row)| {
        if progress.is_canceled() {
            return Err(crate::Error::Canceled);
        }
        for (x, o) in row.iter_mut().enumerate() {
            if *o != NODATA {
                let phi = azimuth.phi(&compass, x, y);
                *o = if lit(k.horizon_sin(x, y, phi), elevation_deg) { LIT } else { SHADOW };
            }
        }
        progress.advance(1);
        Ok(())
    })?;
    Ok(out)
}
