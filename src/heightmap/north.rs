//! Where a DEM's texels lie on the Earth and which way true north points there (SPEC §3.7
//! "True and grid north"): compass azimuths (`azimuth_from=north_cw`) and the sun's azimuth are
//! true azimuths, the kernels' φ counts from the grid's x axis, and on a projected map the two
//! differ by the meridian convergence (about Δλ·sin φ on a transverse Mercator: 1.9° at the
//! edge of a UTM zone at 47° N) — and on a projection that is not conformal (Albers, Lambert
//! equal-area) by more than a rotation.
//!
//! So a true azimuth θ is taken through the projection itself: at a texel, the ground's unit
//! north and east vectors are mapped to pixel space by central differences of the forward
//! projection (steps of [`STEP_M`] on the WGS84 ellipsoid, its meridional and prime-vertical
//! radii), and θ's direction is cos θ·north + sin θ·east there. This holds for any CRS the
//! projection crate reads and any geotransform (rotated or south-up included). The projection is
//! PROJ's, in pure Rust (`proj4rs`), with the EPSG registry's proj strings (`crs-definitions`);
//! a CRS neither knows is baked on grid north with a warning, never guessed.
//!
//! The frames are computed on a lattice every [`LATTICE`] texels and interpolated bilinearly:
//! a convergence varies by ~0.01° across 32 texels of 30 m, so the interpolation error is far
//! below any bin, and a 65 536² map needs 4 M projections, not 4 G.

use super::georef::Georef;
use crate::params::{AzimuthFrom, YAxis};
use proj4rs::proj::Proj;

/// Ground distance of the finite differences, metres.
const STEP_M: f64 = 50.0;
/// Texels between lattice nodes of [`TrueNorth`].
pub const LATTICE: usize = 32;
/// WGS84 semi-major axis and first eccentricity squared.
const WGS84_A: f64 = 6_378_137.0;
const WGS84_E2: f64 = 0.006_694_379_990_14;

/// A DEM's georeferencing as a projection: pixel ↔ (longitude, latitude).
pub struct Geodesy {
    /// The map's CRS and WGS84 longitude/latitude; `None` for a geographic CRS (the transform
    /// gives degrees already).
    proj: Option<(Proj, Proj)>,
    /// GDAL geotransform of the whole map, and the inverse of its linear part.
    t: [f64; 6],
    inv: [f64; 4],
    /// `EPSG:n`, for reports.
    pub crs: String,
}

impl std::fmt::Debug for Geodesy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Geodesy").field("crs", &self.crs).field("transform", &self.t).finish()
    }
}

impl Geodesy {
    /// The projection of a DEM's georeferencing, or why there is none (no CRS, a user-defined
    /// CRS, a CRS the projection crate does not read), in words for a warning.
    pub fn of(g: &Georef) -> Result<Geodesy, String> {
        let t = g.transform().ok_or("the DEM has no map transform")?;
        let det = t[1] * t[5] - t[2] * t[4];
        if det == 0.0 || !det.is_finite() {
            return Err("the DEM's transform is singular".into());
        }
        let inv = [t[5] / det, -t[2] / det, -t[4] / det, t[1] / det];
        let model = g.model();
        let code = g.epsg().ok_or_else(|| match g.geo_keys {
            None => "the DEM has no CRS".to_owned(),
            Some(_) => "the DEM's CRS is user-defined (no EPSG code)".to_owned(),
        })?;
        let crs = format!("EPSG:{code}");
        if model == "geographic" {
            return Ok(Geodesy { proj: None, t, inv, crs });
        }
        if model != "projected" {
            return Err(format!("the DEM's CRS ({crs}) is neither projected nor geographic"));
        }
        let def = crs_definitions::from_code(code)
            .ok_or_else(|| format!("{crs} is not in the EPSG definitions this build carries"))?;
        let src = Proj::from_proj_string(def.proj4)
            .map_err(|e| format!("{crs} ({}) cannot be projected here: {e}", def.proj4))?;
        let geo = Proj::from_proj_string("+proj=longlat +datum=WGS84 +no_defs")
            .map_err(|e| format!("WGS84: {e}"))?;
        let me = Geodesy { proj: Some((src, geo)), t, inv, crs };
        // A CRS whose definition parses but does not invert (an unsupported datum grid) fails
        // here, once, rather than per texel.
        me.lon_lat(0.5, 0.5)
            .ok_or_else(|| format!("{} ({}) does not project here", me.crs, def.proj4))?;
        Ok(me)
    }

    /// Longitude and latitude (degrees) of pixel position (`col`, `row`) of the whole map
    /// (texel (i, j)'s centre is (i + 0.5, j + 0.5)).
    pub fn lon_lat(&self, col: f64, row: f64) -> Option<(f64, f64)> {
        let t = &self.t;
        let x = t[0] + col * t[1] + row * t[2];
        let y = t[3] + col * t[4] + row * t[5];
        let Some((src, geo)) = &self.proj else {
            return Some((x, y));
        };
        let mut p = (x, y, 0.0);
        proj4rs::transform::transform(src, geo, &mut p).ok()?;
        let (lon, lat) = (p.0.to_degrees(), p.1.to_degrees());
        (lon.is_finite() && lat.is_finite()).then_some((lon, lat))
    }

    /// Pixel position of (`lon`, `lat`) in degrees.
    fn pixel(&self, lon: f64, lat: f64) -> Option<(f64, f64)> {
        let (x, y) = match &self.proj {
            None => (lon, lat),
            Some((src, geo)) => {
                let mut p = (lon.to_radians(), lat.to_radians(), 0.0);
                proj4rs::transform::transform(geo, src, &mut p).ok()?;
                (p.0, p.1)
            }
        };
        let (dx, dy) = (x - self.t[0], y - self.t[3]);
        let i = &self.inv;
        let (c, r) = (i[0] * dx + i[1] * dy, i[2] * dx + i[3] * dy);
        (c.is_finite() && r.is_finite()).then_some((c, r))
    }

    /// The ground's unit north and east vectors at (`col`, `row`) in pixel space (pixels per
    /// metre): `[north_col, north_row, east_col, east_row]`.
    pub fn frame(&self, col: f64, row: f64) -> Option<[f64; 4]> {
        let (lon, lat) = self.lon_lat(col, row)?;
        let s = lat.to_radians().sin();
        let w = (1.0 - WGS84_E2 * s * s).sqrt();
        let meridional = WGS84_A * (1.0 - WGS84_E2) / (w * w * w);
        let parallel = WGS84_A / w * lat.to_radians().cos();
        if parallel < 1.0 {
            return None; // at a pole east is undefined
        }
        let dlat = (STEP_M / meridional).to_degrees() / 2.0;
        let dlon = (STEP_M / parallel).to_degrees() / 2.0;
        let (n1, n0) = (self.pixel(lon, lat + dlat)?, self.pixel(lon, lat - dlat)?);
        let (e1, e0) = (self.pixel(lon + dlon, lat)?, self.pixel(lon - dlon, lat)?);
        Some([
            (n1.0 - n0.0) / STEP_M,
            (n1.1 - n0.1) / STEP_M,
            (e1.0 - e0.0) / STEP_M,
            (e1.1 - e0.1) / STEP_M,
        ])
    }
}

/// The tangent-space azimuth φ (radians, SPEC §2) of pixel-space direction (`dc`, `dr`).
fn phi_of(dc: f64, dr: f64, y_axis: YAxis) -> f64 {
    match y_axis {
        YAxis::Up => (-dr).atan2(dc),
        YAxis::Down => dr.atan2(dc),
    }
}

/// True north over a window of a map: the frames of [`Geodesy::frame`] on a lattice, for
/// per-texel conversion of true azimuths to the kernels' φ. The lattice is the whole map's
/// (nodes at map texels 32·i, the last clamped to the map's last texel), whatever the window,
/// so a tile turns each azimuth exactly as the whole map does (SPEC §7.1: tiled bytes are the
/// untiled bake's).
#[derive(Debug, Clone)]
pub struct TrueNorth {
    /// The window's first texel in the map, and the map lattice's first node of the window.
    origin: (usize, usize),
    first: (usize, usize),
    /// Lattice nodes across and down, and their frames, row-major.
    cols: usize,
    rows: usize,
    frames: Vec<[f64; 4]>,
    y_axis: YAxis,
    pub crs: String,
}

impl TrueNorth {
    /// The lattice of the `w` × `h` window whose texel (0, 0) is texel (`x0`, `y0`) of the map
    /// `geo` describes; `None` where the projection fails at a node (a window reaching a pole
    /// or past the projection's domain).
    pub fn new(
        geo: &Geodesy,
        (x0, y0): (usize, usize),
        (w, h): (usize, usize),
        (mw, mh): (usize, usize),
        y_axis: YAxis,
    ) -> Option<TrueNorth> {
        let first = (x0 / LATTICE, y0 / LATTICE);
        let cols = (x0 + w.max(1) - 1) / LATTICE + 2 - first.0;
        let rows = (y0 + h.max(1) - 1) / LATTICE + 2 - first.1;
        let mut frames = Vec::with_capacity(cols * rows);
        for j in 0..rows {
            for i in 0..cols {
                let c = ((first.0 + i) * LATTICE).min(mw.saturating_sub(1)) as f64 + 0.5;
                let r = ((first.1 + j) * LATTICE).min(mh.saturating_sub(1)) as f64 + 0.5;
                frames.push(geo.frame(c, r)?);
            }
        }
        let crs = geo.crs.clone();
        Some(TrueNorth { origin: (x0, y0), first, cols, rows, frames, y_axis, crs })
    }

    /// The interpolated frame at window texel (`x`, `y`).
    fn frame_at(&self, x: usize, y: usize) -> [f64; 4] {
        let (mx, my) = (self.origin.0 + x, self.origin.1 + y);
        let (fx, fy) = (mx as f64 / LATTICE as f64, my as f64 / LATTICE as f64);
        let i = (fx as usize).clamp(self.first.0, self.first.0 + self.cols - 2);
        let j = (fy as usize).clamp(self.first.1, self.first.1 + self.rows - 2);
        let (u, v) = ((fx - i as f64).min(1.0), (fy - j as f64).min(1.0));
        let (i, j) = (i - self.first.0, j - self.first.1);
        let at = |a: usize, b: usize| &self.frames[b * self.cols + a];
        let (f00, f10, f01, f11) = (at(i, j), at(i + 1, j), at(i, j + 1), at(i + 1, j + 1));
        std::array::from_fn(|k| {
            (f00[k] * (1.0 - u) + f10[k] * u) * (1.0 - v) + (f01[k] * (1.0 - u) + f11[k] * u) * v
        })
    }

    /// φ (radians) of true azimuth `theta_deg` (clockwise from true north) at window texel
    /// (`x`, `y`).
    pub fn phi(&self, x: usize, y: usize, theta_deg: f64) -> f64 {
        let f = self.frame_at(x, y);
        let (s, c) = theta_deg.to_radians().sin_cos();
        phi_of(c * f[0] + s * f[2], c * f[1] + s * f[3], self.y_axis)
    }

    /// The grid bearing of true north at window texel (`x`, `y`): degrees clockwise from the
    /// image's up (minus the meridian convergence in the usual sign), for reports.
    pub fn north_bearing_deg(&self, x: usize, y: usize) -> f64 {
        let f = self.frame_at(x, y);
        f[0].atan2(-f[1]).to_degrees()
    }
}

/// How a true azimuth becomes the kernels' φ over a window: through [`TrueNorth`], or, on a map
/// without a projection (an image, a CRS not read), on the grid: north is up the image.
#[derive(Debug, Clone)]
pub enum Compass {
    Grid(YAxis),
    True(TrueNorth),
}

impl Compass {
    /// φ (radians) of true azimuth `theta_deg` at window texel (`x`, `y`).
    #[inline]
    pub fn phi(&self, x: usize, y: usize, theta_deg: f64) -> f64 {
        match self {
            Compass::Grid(y_axis) => {
                crate::terrain::profile::tangent_azimuth(theta_deg, AzimuthFrom::NorthCw, *y_axis)
            }
            Compass::True(t) => t.phi(x, y, theta_deg),
        }
    }

    /// Whether azimuths go through a projection.
    pub fn is_true(&self) -> bool {
        matches!(self, Compass::True(_))
    }
}

/// What bake.json and the bake resource say of north (SPEC §3.7: "Band descriptions and
/// bake.json say which").
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct NorthReport {
    /// `true`: compass and sun azimuths are true azimuths, converted per texel; `grid`: north is
    /// up the image.
    pub reference: &'static str,
    /// The grid bearing of true north at the map's centre, degrees clockwise from up.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub north_bearing_deg: Option<f64>,
    /// The CRS the conversion projected with.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub crs: Option<String>,
    /// Why a DEM is on grid north.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

/// The compass of the `size` window at `origin` of a `map`-sized map georeferenced by
/// `georef`, and what to report; a map without a DEM's georeferencing is on grid north without a reason (an
/// image's "north" is up by definition).
pub fn compass(
    georef: Option<&Georef>,
    origin: (usize, usize),
    size: (usize, usize),
    map: (usize, usize),
    y_axis: YAxis,
) -> (Compass, NorthReport) {
    let grid = |reason: Option<String>| {
        let report = NorthReport { reference: "grid", north_bearing_deg: None, crs: None, reason };
        (Compass::Grid(y_axis), report)
    };
    let Some(g) = georef.filter(|g| g.is_dem()) else {
        return grid(None);
    };
    let geo = match Geodesy::of(g) {
        Ok(geo) => geo,
        Err(why) => return grid(Some(why)),
    };
    match TrueNorth::new(&geo, origin, size, map, y_axis) {
        Some(t) => {
            // The map's centre, whatever the window (a tile reports the whole map's).
            let centre = TrueNorth::new(&geo, (0, 0), map, map, y_axis);
            let bearing = centre.map_or(f64::NAN, |c| c.north_bearing_deg(map.0 / 2, map.1 / 2));
            let report = NorthReport {
                reference: "true",
                north_bearing_deg: Some((bearing * 1e6).round() / 1e6),
                crs: Some(t.crs.clone()),
                reason: None,
            };
            (Compass::True(t), report)
        }
        None => grid(Some(format!("{} does not project over the whole map", geo.crs))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::heightmap::georef::CrsModel;

    fn utm32(x0: f64, y0: f64, cell: f64) -> Georef {
        Georef::from_gdal(
            [x0, cell, 0.0, y0, 0.0, -cell],
            Some(CrsModel::Projected),
            32632,
            9001,
            None,
        )
    }

    #[test]
    fn a_utm_map_off_its_central_meridian_has_its_convergence() {
        // 700 000 E, 5 200 000 N in zone 32: 11.627° E, 46.923° N, 2.63° east of the central
        // meridian 9° E; GDAL's transform of the same point puts true north at -1.91950° (the
        // same finite difference, taken by rasterio).
        let g = utm32(700_000.0 - 0.5 * 30.0, 5_200_000.0 + 0.5 * 30.0, 30.0);
        let geo = Geodesy::of(&g).unwrap();
        let (lon, lat) = geo.lon_lat(0.5, 0.5).unwrap();
        assert!((lon - 11.627_001).abs() < 1e-5 && (lat - 46.923_381).abs() < 1e-5, "{lon} {lat}");
        let t = TrueNorth::new(&geo, (0, 0), (64, 64), (64, 64), YAxis::Up).unwrap();
        let b = t.north_bearing_deg(0, 0);
        assert!((b + 1.919_50).abs() < 1e-4, "{b}");
        // Conformal: east is north turned 90°, at the same scale.
        let f = geo.frame(0.5, 0.5).unwrap();
        let (n, e) = (f[0].hypot(f[1]), f[2].hypot(f[3]));
        assert!((n / e - 1.0).abs() < 1e-6 && (f[0] * f[2] + f[1] * f[3]).abs() < 1e-6 * n * e);
        // True azimuth 0 is grid bearing -1.92°: φ = 90° + 1.92° with y up, -90° + 1.92°... down.
        let up = t.phi(0, 0, 0.0).to_degrees();
        assert!((up - (90.0 + 1.919_50)).abs() < 1e-4, "{up}");
        let down = TrueNorth::new(&geo, (0, 0), (64, 64), (64, 64), YAxis::Down).unwrap();
        let d = down.phi(0, 0, 0.0).to_degrees();
        assert!((d - (-90.0 - 1.919_50)).abs() < 1e-4, "{d}");
    }

    #[test]
    fn on_the_central_meridian_and_on_a_lat_lon_grid_true_is_grid() {
        // Texel (0, 0)'s centre is 15 m east of the central meridian: 0.0001° of convergence.
        let g = utm32(500_000.0, 5_200_000.0, 30.0);
        let (c, report) = compass(Some(&g), (0, 0), (1, 1), (1, 1), YAxis::Up);
        assert_eq!(report.reference, "true");
        for theta in [0.0, 37.0, 90.0, 200.0] {
            let grid =
                crate::terrain::profile::tangent_azimuth(theta, AzimuthFrom::NorthCw, YAxis::Up);
            let d = (c.phi(0, 0, theta) - grid).rem_euclid(std::f64::consts::TAU);
            assert!(d.min(std::f64::consts::TAU - d) < 1e-5, "{theta}: {d}");
        }
        let ll = Georef::from_gdal(
            [6.0, 0.001, 0.0, 47.0, 0.0, -0.001],
            Some(CrsModel::Geographic),
            4326,
            0,
            None,
        );
        let (c, report) = compass(Some(&ll), (0, 0), (100, 100), (100, 100), YAxis::Up);
        assert_eq!(report.reference, "true");
        assert!((c.phi(50, 50, 0.0).to_degrees() - 90.0).abs() < 1e-6);
    }

    #[test]
    fn the_lattice_interpolates_within_a_hundredth_of_a_degree() {
        let g = utm32(680_000.0, 5_250_000.0, 30.0);
        let geo = Geodesy::of(&g).unwrap();
        let t = TrueNorth::new(&geo, (100, 40), (300, 200), (500, 300), YAxis::Up).unwrap();
        let whole = TrueNorth::new(&geo, (0, 0), (500, 300), (500, 300), YAxis::Up).unwrap();
        for (x, y) in [(0, 0), (17, 5), (150, 99), (299, 199), (211, 3)] {
            let f = geo.frame((100 + x) as f64 + 0.5, (40 + y) as f64 + 0.5).unwrap();
            let exact = f[0].atan2(-f[1]).to_degrees();
            assert!((t.north_bearing_deg(x, y) - exact).abs() < 1e-2, "({x}, {y})");
            // A window turns azimuths exactly as the whole map (tiles' bytes are the map's).
            for theta in [0.0, 123.4] {
                assert_eq!(t.phi(x, y, theta), whole.phi(100 + x, 40 + y, theta));
            }
        }
    }

    #[test]
    fn a_map_without_a_projection_is_on_grid_north_and_says_why() {
        let mut g = utm32(500_000.0, 5_200_000.0, 30.0);
        let (_, r) = compass(None, (0, 0), (8, 8), (8, 8), YAxis::Up);
        assert_eq!((r.reference, r.reason), ("grid", None));
        g = Georef { geo_keys: None, ..g };
        let (_, r) = compass(Some(&g), (0, 0), (8, 8), (8, 8), YAxis::Up);
        assert_eq!(r.reference, "grid");
        let user = Georef::from_gdal(
            [0.0, 1.0, 0.0, 0.0, 0.0, -1.0],
            Some(CrsModel::Projected),
            0,
            9001,
            None,
        );
        let (c, r) = compass(Some(&user), (0, 0), (8, 8), (8, 8), YAxis::Up);
        assert!(!c.is_true() && r.reason.unwrap().contains("user-defined"));
    }
}
