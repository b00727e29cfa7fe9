//! The products of one exact ray per texel and azimuth (SPEC §3.7): openness, horizon
//! distance, the sun's shadow, sun hours and insolation, the horizon profile, and compass bands
//! on a projected map. What they share, and why they are not the kernels' bins: each asks for
//! an azimuth per texel (the sun's, or a true azimuth turned by the meridian convergence
//! there, [`crate::heightmap::north`]) or for something a bin keeps no trace of (the point that
//! sets the horizon, a signed elevation), so each walks `exact`'s ray itself, whatever the
//! bake's method, row by row on the rayon pool with cancellation between rows.

use super::{bake_horizon, check_scaled, curvature, resolve_radius};
use crate::error::Result;
use crate::heightmap::HeightMap;
use crate::kernels::{self, Grid};
use crate::params::{BakeParams, Method, Radius};
use crate::progress::{Progress, Stage};

/// Positive and negative openness (SPEC §3.7, Yokoyama et al. 2002, as RVT computes them), in
/// degrees: the mean over the `bins` azimuths of 90° − β_n, β_n the signed maximum elevation
/// angle within `radius` texels (no clamp at 0), on the surface and on the inverted surface −h;
/// by the plain cell walk over the bilinear surface ([`kernels::exact::signed_elevation`]),
/// without the earth-curvature drop (as RVT), holes no surface; an azimuth whose ray meets no
/// surface (no length at an `edge=none` border, or holes only) is left out of the mean.
/// `nodata` at holes.
///
/// # Errors
/// [`crate::Error::Canceled`].
pub(super) fn openness_planes(
    grid: Grid<'_>,
    params: &BakeParams,
    radius: u32,
    holes: Option<&[bool]>,
    nodata: f32,
    progress: &Progress,
) -> Result<[Vec<f32>; 2]> {
    use rayon::prelude::*;
    let (w, h) = (grid.width, grid.height);
    let inverted: Vec<f32> = grid.heights.iter().map(|v| -v).collect();
    let grids = [grid, Grid::new(w, h, &inverted, params.edge, params.y_axis)];
    let nb = params.bins as usize;
    let phis: Vec<f64> = (0..nb).map(|n| n as f64 * std::f64::consts::TAU / nb as f64).collect();
    let r = f64::from(radius);
    let mut planes = [vec![nodata; w * h], vec![nodata; w * h]];
    progress.start(Stage::Bake, 2 * h as u64);
    for (g, plane) in grids.iter().zip(planes.iter_mut()) {
        plane.par_chunks_mut(w).enumerate().try_for_each(|(y, row)| {
            if progress.is_canceled() {
                return Err(crate::Error::Canceled);
            }
            for (x, o) in row.iter_mut().enumerate() {
                if holes.is_some_and(|m| m[y * w + x]) {
                    continue;
                }
                let (mut sum, mut n) = (0.0f64, 0usize);
                for &phi in &phis {
                    if let Some(beta) = kernels::exact::signed_elevation(g, holes, x, y, phi, r) {
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
pub(super) fn horizon_distances(
    grid: Grid<'_>,
    params: &BakeParams,
    radius: u32,
    holes: Option<&[bool]>,
    nodata: f32,
    progress: &Progress,
) -> Result<Vec<f32>> {
    use rayon::prelude::*;
    let (w, h, nb) = (grid.width, grid.height, params.bins as usize);
    let order = crate::terrain::angles::band_bins(nb, params.azimuth_from, params.y_axis);
    let r = (params.radius != Radius::Unlimited || params.max_distance.is_some()).then_some(radius);
    let k = kernels::exact::ExactHorizon::new(grid, r, params.bins, crate::params::Reduce::Point)
        .with_curvature(curvature(params))
        .with_holes(holes);
    let unit = params.cell_size.unwrap_or(1.0);
    // Texel-major rows (each texel's bands together), then transposed to band planes.
    let mut texels = vec![nodata; w * h * nb];
    progress.start(Stage::Bake, h as u64);
    texels.par_chunks_mut(w * nb).enumerate().try_for_each(|(y, row)| {
        if progress.is_canceled() {
            return Err(crate::Error::Canceled);
        }
        for (x, bands) in row.chunks_exact_mut(nb).enumerate() {
            if holes.is_some_and(|m| m[y * w + x]) {
                continue;
            }
            for (band, o) in bands.iter_mut().enumerate() {
                let (t, s) = k.horizon_and_distance(x, y, order[band]);
                if t > 0.0 {
                    *o = (s * unit) as f32;
                }
            }
        }
        progress.advance(1);
        Ok(())
    })?;
    let plane = w * h;
    let mut planes = vec![nodata; plane * nb];
    for (t, bands) in texels.chunks_exact(nb).enumerate() {
        for (band, &v) in bands.iter().enumerate() {
            planes[band * plane + t] = v;
        }
    }
    Ok(planes)
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
    Ok(crate::terrain::profile::profile(bins, params.azimuth_from, params.y_axis, |phi| {
        k.horizon_sin(x, y, phi)
    }))
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
    azimuth_deg: f64,
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
    let phi =
        crate::terrain::profile::tangent_azimuth(azimuth_deg, params.azimuth_from, params.y_axis);
    if params.method == Method::Lengyel {
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
    let r = (params.radius != Radius::Unlimited || params.max_distance.is_some())
        .then_some(radius.texels);
    let k = kernels::exact::ExactHorizon::new(grid, r, 16, crate::params::Reduce::Point)
        .with_curvature(curvature(params))
        .with_holes(holes);
    progress.start(Stage::Bake, h as u64);
    out.par_chunks_mut(w).enumerate().try_for_each(|(y, row)| {
        if progress.is_canceled() {
            return Err(crate::Error::Canceled);
        }
        for (x, o) in row.iter_mut().enumerate() {
            if *o != NODATA {
                *o = if lit(k.horizon_sin(x, y, phi), elevation_deg) { LIT } else { SHADOW };
            }
        }
        progress.advance(1);
        Ok(())
    })?;
    Ok(out)
}
