//! The native half of the `horizon_bake` Python package: the library's bake on numpy arrays.
//!
//! It is a thin edge, like the CLI and the HTTP handlers: arrays become a [`HeightMap`] through
//! the same constructor every decoder ends in ([`HeightMap::from_samples`]), keyword parameters
//! become [`BakeParams`] through the same textual pairs the CLI and the service parse, the DEM
//! defaults and method fitting are the CLI's, and the bake is [`horizon_bake::bake`]'s. So an
//! array and the same image in a file bake to the same values. What is Python's (argument
//! conversion, the result object, the exception classes) lives in `horizon_bake/*.py`; this
//! module only does what needs the library.
//!
//! A bake runs on its own thread (the kernels on rayon's pool) with the GIL released; the
//! calling thread wakes every few tens of milliseconds to report progress to the callback and to
//! check for KeyboardInterrupt. A callback that returns `False` or raises, and Ctrl-C, cancel
//! the bake through [`Progress::cancel`], which the kernels check between bands of rows.

use horizon_bake::bake::{self as hb, Precisions, ResolvedRadius};
use horizon_bake::heightmap::georef::{apply_dem_defaults, CrsModel, Georef};
use horizon_bake::heightmap::HeightMap;
use horizon_bake::params::BakeParams;
use horizon_bake::progress::Progress;
use horizon_bake::Error;
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// How often the waiting thread reports progress and checks for Ctrl-C.
const POLL: Duration = Duration::from_millis(50);

/// The library's error as the package's exception (`horizon_bake._errors`), with the message the
/// CLI prints after `horizon-bake: `, the problem+json `code`, and the parameter's name for a
/// parameter error.
fn raise(py: Python<'_>, e: Error) -> PyErr {
    let class = match &e {
        Error::Param { .. } => "ParameterError",
        Error::Decode(_) | Error::Unsupported(_) | Error::InvalidInput(_) => "InputError",
        Error::Limits(_) | Error::MemoryBusy { .. } => "LimitError",
        Error::Canceled => "Canceled",
        _ => "HorizonBakeError",
    };
    let field = match &e {
        Error::Param { field, .. } => Some(field.as_str()),
        _ => None,
    };
    raise_as(py, class, &e.to_string(), e.code(), field)
}

/// An exception of class `class` of `horizon_bake._errors`.
fn raise_as(py: Python<'_>, class: &str, message: &str, code: &str, field: Option<&str>) -> PyErr {
    let made = py.import("horizon_bake._errors").and_then(|m| {
        let kwargs = PyDict::new(py);
        kwargs.set_item("code", code)?;
        kwargs.set_item("field", field)?;
        m.getattr(class)?.call((message,), Some(&kwargs))
    });
    match made {
        Ok(exc) => PyErr::from_value(exc),
        Err(err) => err,
    }
}

/// Heights from a 2-D array of `uint8`, `uint16` or `float32` (the Python side converts every
/// other dtype to `float32`), normalised as the image decoders do when `normalise` (integers to
/// [0, 1], kept as stored × 255 or × 65535 for nodata), as-is otherwise (a DEM's samples).
fn samples(heights: &Bound<'_, PyAny>, normalise: bool) -> PyResult<(usize, usize, Vec<f32>, f64)> {
    fn collect<T: numpy::Element + Copy>(
        a: &PyReadonlyArray2<'_, T>,
        f: impl Fn(T) -> f32,
    ) -> (usize, usize, Vec<f32>) {
        let (h, w) = (a.shape()[0], a.shape()[1]);
        let values = match a.as_slice() {
            Ok(s) => s.iter().map(|&v| f(v)).collect(),
            Err(_) => a.as_array().iter().map(|&v| f(v)).collect(),
        };
        (w, h, values)
    }
    if let Ok(a) = heights.extract::<PyReadonlyArray2<'_, u8>>() {
        let (w, h, v) = collect(&a, |v| if normalise { v as f32 / 255.0 } else { v as f32 });
        return Ok((w, h, v, if normalise { 255.0 } else { 1.0 }));
    }
    if let Ok(a) = heights.extract::<PyReadonlyArray2<'_, u16>>() {
        let (w, h, v) =
            collect(&a, |v| if normalise { (v as f64 / 65535.0) as f32 } else { v as f32 });
        return Ok((w, h, v, if normalise { 65535.0 } else { 1.0 }));
    }
    let a = heights.extract::<PyReadonlyArray2<'_, f32>>()?;
    let (w, h, v) = collect(&a, |v| v);
    Ok((w, h, v, 1.0))
}

/// The georeferencing of `(transform, model, epsg, linear_unit)` from the Python side, with the
/// nodata the parameters declare as GDAL_NODATA (so `nodata=auto` finds it).
fn georef_of(georef: Option<GeorefArg>, nodata: Option<f64>) -> PyResult<Option<Georef>> {
    let Some((t, model, epsg, unit)) = georef else { return Ok(None) };
    let model = match model.as_str() {
        "projected" => Some(CrsModel::Projected),
        "geographic" => Some(CrsModel::Geographic),
        "none" => None,
        other => {
            return Err(pyo3::exceptions::PyValueError::new_err(format!(
                "crs model `{other}`: projected, geographic or none"
            )))
        }
    };
    Ok(Some(Georef::from_gdal(t, model, epsg, unit, nodata)))
}

/// The georeferencing as the Python side passes it: (GDAL geotransform, "projected" |
/// "geographic" | "none", EPSG code or 0, EPSG linear unit code).
type GeorefArg = ([f64; 6], String, u16, u16);

/// The parameters of `pairs` (values as the CLI's flags spell them), checked as far as they can
/// be before the map is known; the full check runs with the DEM defaults.
fn parse_params(py: Python<'_>, pairs: &[(String, String)]) -> PyResult<BakeParams> {
    let params =
        BakeParams::from_pairs_unchecked(pairs.iter().map(|(k, v)| (k.as_str(), v.as_str())))
            .map_err(|e| raise(py, e))?;
    params.check_before_input().map_err(|e| raise(py, e))?;
    Ok(params)
}

/// The nodata value `params` declares (NaN for `nan`), for the GDAL_NODATA of an array's
/// georeferencing.
fn declared_nodata(params: &BakeParams) -> Option<f64> {
    match params.nodata {
        horizon_bake::params::NoData::Value(v) => Some(v),
        horizon_bake::params::NoData::Nan => Some(f64::NAN),
        _ => None,
    }
}

/// What one bake made, before it becomes Python objects.
#[derive(Default)]
struct Made {
    radius: Option<ResolvedRadius>,
    layers: Option<hb::HorizonLayers>,
    fourier: Option<horizon_bake::kernels::fourier::FourierLayers>,
    terrain: Option<hb::TerrainProducts>,
    surface: Option<hb::SurfaceMaps>,
    bake_ms: f64,
}

fn ms(t: Instant) -> f64 {
    (t.elapsed().as_secs_f64() * 1e6).round() / 1e3
}

/// Runs the products `params.outputs` asks for, one after the other (terrain, surface maps,
/// horizon, Fourier, as the pipeline orders them); `step` counts the finished ones for the overall
/// progress.
fn run(
    map: &HeightMap,
    params: &BakeParams,
    precisions: Precisions,
    progress: &Progress,
    step: &AtomicUsize,
) -> horizon_bake::Result<Made> {
    let t = Instant::now();
    let mut made = Made::default();
    if params.outputs.terrain() {
        let (p, r) = hb::bake_terrain(map, params, progress)?;
        made.terrain = Some(p);
        made.radius = Some(r);
        next(progress, step);
    }
    if params.outputs.surface() {
        let (m, r) = hb::bake_surface(map, params, progress)?;
        made.surface = Some(m);
        made.radius = Some(r);
        next(progress, step);
    }
    if params.outputs.horizon {
        let (l, r) = hb::bake_horizon(map, params, precisions, progress)?;
        made.layers = Some(l);
        made.radius = Some(r);
        next(progress, step);
    }
    if params.outputs.fourier {
        let (f, r) = hb::bake_fourier(map, params, progress)?;
        made.fourier = Some(f);
        made.radius.get_or_insert(r);
        next(progress, step);
    }
    made.bake_ms = ms(t);
    Ok(made)
}

/// Marks a product done: the stage's fraction back to 0 first, so the overall fraction never
/// counts a finished product twice (done + its stale 1.0).
fn next(progress: &Progress, step: &AtomicUsize) {
    progress.start(horizon_bake::progress::Stage::Queued, 1);
    step.fetch_add(1, Ordering::Relaxed);
}

/// Runs `work` on its own thread with the GIL released; meanwhile calls `callback(fraction)`
/// (overall, 0..1, over `steps` products) every [`POLL`] and checks for signals. A callback
/// returning `False` or raising, and KeyboardInterrupt, cancel the bake and are returned.
fn with_progress<T: Send>(
    py: Python<'_>,
    progress: &Progress,
    step: &AtomicUsize,
    steps: usize,
    callback: Option<&Bound<'_, PyAny>>,
    work: impl FnOnce() -> horizon_bake::Result<T> + Send,
) -> PyResult<T> {
    let (tx, rx) = std::sync::mpsc::channel();
    // Waited on with the GIL released, which asks for a `Sync` borrow.
    let rx = std::sync::Mutex::new(rx);
    std::thread::scope(|s| {
        s.spawn(move || {
            // A panic in the library is a bug; it reaches Python as an error, not an abort.
            let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(work))
                .unwrap_or_else(|_| Err(Error::Internal("the bake panicked".into())));
            let _ = tx.send(r);
        });
        let mut interrupt: Option<PyErr> = None;
        let mut last = 0.0f64;
        loop {
            match py.detach(|| match rx.lock() {
                Ok(rx) => rx.recv_timeout(POLL),
                Err(_) => Err(std::sync::mpsc::RecvTimeoutError::Disconnected),
            }) {
                Ok(r) => {
                    return match (interrupt, r) {
                        (Some(e), _) => Err(e),
                        (None, r) => r.map_err(|e| raise(py, e)),
                    };
                }
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
                    return Err(raise(py, Error::Internal("the bake thread ended".into())));
                }
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
            }
            if interrupt.is_some() {
                continue;
            }
            if let Err(e) = py.check_signals() {
                progress.cancel();
                interrupt = Some(e);
                continue;
            }
            if let Some(cb) = callback {
                let done = step.load(Ordering::Relaxed).min(steps.saturating_sub(1));
                let overall = (done as f64 + progress.fraction()) / steps.max(1) as f64;
                // Read between a product's end and the step count: never report less than before.
                last = last.max(overall.clamp(0.0, 1.0));
                match cb.call1((last,)) {
                    Ok(v) if v.is(&*pyo3::types::PyBool::new(py, false)) => {
                        progress.cancel();
                    }
                    Ok(_) => {}
                    Err(e) => {
                        progress.cancel();
                        interrupt = Some(e);
                    }
                }
            }
        }
    })
}

/// A row-major `Vec` as a numpy array of `shape`, owning the vector (no copy).
fn array<'py, T: numpy::Element>(
    py: Python<'py>,
    v: Vec<T>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyAny>> {
    Ok(PyArray1::from_vec(py, v).reshape(shape.to_vec())?.into_any())
}

/// Bakes a 2-D array. `pairs` are the parameters as the CLI's flags spell their values;
/// `georef` = (GDAL geotransform, "projected"|"geographic", EPSG code, EPSG linear unit) of a
/// DEM; `precision` picks the horizon layers' type: `uint8` (the png8 values), `uint16` (png16)
/// or `float32`. Returns a dict the Python side wraps in its result object.
#[pyfunction]
#[pyo3(signature = (heights, pairs, georef=None, normalise=true, precision="uint8", progress=None))]
fn bake_array<'py>(
    py: Python<'py>,
    heights: &Bound<'py, PyAny>,
    pairs: Vec<(String, String)>,
    georef: Option<GeorefArg>,
    normalise: bool,
    precision: &str,
    progress: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let total = Instant::now();
    let precisions = match precision {
        "uint8" => Precisions { u8: true, u16: false, f32: false },
        "uint16" => Precisions { u8: false, u16: true, f32: false },
        "float32" => Precisions { u8: false, u16: false, f32: true },
        other => {
            return Err(raise(
                py,
                Error::param("dtype", format!("`{other}`: uint8, uint16 or float32")),
            ))
        }
    };
    let mut params = parse_params(py, &pairs)?;
    let t = Instant::now();
    let georef = georef_of(georef, declared_nodata(&params))?;
    let normalise = normalise && georef.is_none();
    let (w, h, values, stored) = samples(heights, normalise)?;
    let map = py
        .detach(|| HeightMap::from_samples(w, h, values, stored, params.nodata, georef))
        .map_err(|e| raise(py, e))?;
    let warnings = map.dem_warnings();
    apply_dem_defaults(&mut params, map.terrain.georef.as_ref()).map_err(|e| raise(py, e))?;
    hb::fit_method(&mut params, w as u32, h as u32, false).map_err(|e| raise(py, e))?;
    let decode_ms = ms(t);

    let progress_handle = Progress::new();
    let step = AtomicUsize::new(0);
    let steps = [
        params.outputs.terrain(),
        params.outputs.surface(),
        params.outputs.horizon,
        params.outputs.fourier,
    ]
    .iter()
    .filter(|&&b| b)
    .count();
    let made = with_progress(py, &progress_handle, &step, steps, progress, || {
        run(&map, &params, precisions, &progress_handle, &step)
    })?;

    let out = PyDict::new(py);
    out.set_item("width", w)?;
    out.set_item("height", h)?;
    let resolved = PyDict::new(py);
    for (k, v) in params.to_pairs() {
        resolved.set_item(k, v)?;
    }
    out.set_item("params", resolved)?;
    if let Some(r) = &made.radius {
        let radius = PyDict::new(py);
        radius.set_item("texels", r.texels)?;
        radius.set_item("reason", &r.reason)?;
        out.set_item("resolved_radius", radius)?;
    }
    out.set_item("warnings", PyList::new(py, warnings)?)?;
    out.set_item(
        "holes",
        map.terrain.holes.as_ref().map_or(0, |h| h.iter().filter(|&&b| b).count()),
    )?;
    out.set_item("nodata", map.terrain.nodata)?;
    if let Some(l) = made.layers {
        let shape = [l.height, l.width, 4];
        let pair = if let Some([a, b]) = l.u8 {
            (array(py, a, &shape)?, array(py, b, &shape)?)
        } else if let Some([a, b]) = l.u16 {
            (array(py, a, &shape)?, array(py, b, &shape)?)
        } else if let Some([a, b]) = l.f32 {
            (array(py, a, &shape)?, array(py, b, &shape)?)
        } else {
            return Err(raise(py, Error::Internal("no horizon layers were quantised".into())));
        };
        out.set_item("layers", pair)?;
    }
    if let Some(f) = made.fourier {
        let d = PyDict::new(py);
        d.set_item("terms", f.terms)?;
        d.set_item("bands", array(py, f.bands, &[f.height, f.width, 4])?)?;
        d.set_item("constant", array(py, f.constant, &[f.height, f.width])?)?;
        match f.high {
            Some(hi) => d.set_item("high", array(py, hi, &[f.height, f.width, 4])?)?,
            None => d.set_item("high", py.None())?,
        }
        out.set_item("fourier", d)?;
    }
    if let Some(t) = made.terrain {
        if let Some(a) = t.angles {
            out.set_item("angles", array(py, a, &[t.bins, t.height, t.width])?)?;
        }
        if let Some(s) = t.svf {
            out.set_item("svf", array(py, s, &[t.height, t.width])?)?;
        }
        if let Some(d) = t.distance {
            out.set_item("horizon_distance", array(py, d, &[t.bins, t.height, t.width])?)?;
        }
        if let Some([pos, neg]) = t.openness {
            out.set_item("openness_positive", array(py, pos, &[t.height, t.width])?)?;
            out.set_item("openness_negative", array(py, neg, &[t.height, t.width])?)?;
        }
        if let Some(v) = t.sun_hours {
            out.set_item("sun_hours", array(py, v, &[t.height, t.width])?)?;
        }
        if let Some(v) = t.insolation {
            out.set_item("insolation", array(py, v, &[t.height, t.width])?)?;
        }
        out.set_item("product_nodata", t.nodata)?;
    }
    if let Some(m) = made.surface {
        let (w, h) = (m.width, m.height);
        if let Some(n) = m.normal {
            out.set_item("normal", array(py, n, &[h, w, 3])?)?;
        }
        if let Some(a) = m.ao {
            out.set_item("ao", array(py, a, &[h, w])?)?;
        }
        if let Some(b) = m.bent_normal {
            let ch = b.len() / (w * h).max(1);
            out.set_item("bent_normal", array(py, b, &[h, w, ch])?)?;
        }
    }
    let timings = PyDict::new(py);
    timings.set_item("decode", decode_ms)?;
    timings.set_item("bake", made.bake_ms)?;
    timings.set_item("total", ms(total))?;
    out.set_item("timings_ms", timings)?;
    Ok(out)
}

/// The terrain products of one block of a map cut in blocks (`horizon_bake.dask`), equal per
/// texel to the whole map's bake: `block` is the block with its halo (heights as-is), `interior`
/// = (column, row, width, height) of the block inside it, `pairs` the whole map's resolved
/// parameters ([`resolve`]), `stats` = (lowest, highest) height of the whole map's texels that
/// are not holes and whether it has any hole, `radius` the whole map's radius in texels. Holes
/// are filled as the whole map's ([`horizon_bake::heightmap::hole_fill`]) and the kernels see
/// the whole map's height range, as a tiled bake's tiles do ([`hb::bake_terrain_window`]).
/// Returns (angles `(bins, h, w)` or `None`, svf `(h, w)` or `None`).
#[pyfunction]
#[pyo3(signature = (block, interior, pairs, stats, radius, georef=None))]
#[allow(clippy::type_complexity)]
fn bake_block<'py>(
    py: Python<'py>,
    block: &Bound<'py, PyAny>,
    interior: (usize, usize, usize, usize),
    pairs: Vec<(String, String)>,
    stats: (f32, f32, bool),
    radius: u32,
    georef: Option<GeorefArg>,
) -> PyResult<(Option<Bound<'py, PyAny>>, Option<Bound<'py, PyAny>>)> {
    let mut params = parse_params(py, &pairs)?;
    let georef = georef_of(georef, declared_nodata(&params))?;
    let (w, h, values, stored) = samples(block, false)?;
    let (lo, hi, any_hole) = stats;
    let fill = horizon_bake::heightmap::hole_fill(lo, hi);
    let mut map =
        HeightMap::from_samples_filled(w, h, values, stored, params.nodata, georef, Some(fill))
            .map_err(|e| raise(py, e))?;
    if any_hole && map.terrain.holes.is_none() {
        // As a tiled bake's window (`TileHeights::into_map`): a hole mask whenever the whole
        // map has holes, so the kernels take the same (hole-aware) path as on the whole map.
        map.terrain.holes = Some(vec![false; w * h]);
    }
    apply_dem_defaults(&mut params, map.terrain.georef.as_ref()).map_err(|e| raise(py, e))?;
    // MapStats::scaled_range of the whole map: its lowest value is the fill when it has holes.
    let lowest = if any_hole { fill } else { lo };
    let (a, b) =
        ((lowest as f64 * params.height_scale) as f32, (hi as f64 * params.height_scale) as f32);
    let range = (a.min(b), a.max(b));
    let progress = Progress::new();
    let t = py
        .detach(|| hb::bake_terrain_window(map, &params, interior, None, range, radius, &progress))
        .map_err(|e| raise(py, e))?;
    let (iw, ih) = (t.width, t.height);
    let angles = t.angles.map(|v| array(py, v, &[t.bins, ih, iw])).transpose()?;
    let svf = t.svf.map(|v| array(py, v, &[ih, iw])).transpose()?;
    Ok((angles, svf))
}

/// The parameters a bake of a `width × height` map with `georef` would run with (the DEM
/// defaults applied, the method fitted), as pairs, and the radius in texels when it does not
/// depend on the heights (`None` for `radius=auto` without `max_distance`). For bakes cut in
/// blocks (`horizon_bake.dask`): each block runs with the whole map's parameters.
#[pyfunction]
#[pyo3(signature = (pairs, width, height, georef=None))]
fn resolve<'py>(
    py: Python<'py>,
    pairs: Vec<(String, String)>,
    width: usize,
    height: usize,
    georef: Option<GeorefArg>,
) -> PyResult<(Bound<'py, PyDict>, Option<u32>)> {
    let mut params = parse_params(py, &pairs)?;
    let georef = georef_of(georef, None)?;
    apply_dem_defaults(&mut params, georef.as_ref()).map_err(|e| raise(py, e))?;
    hb::fit_method(&mut params, width as u32, height as u32, false).map_err(|e| raise(py, e))?;
    let mut by_heights = false;
    let r = hb::resolve_radius_in(&params, width, height, || {
        by_heights = true;
        (0.0, 0.0)
    });
    let out = PyDict::new(py);
    for (k, v) in params.to_pairs() {
        out.set_item(k, v)?;
    }
    Ok((out, (!by_heights).then_some(r.texels)))
}

/// The channel-factor cube map of face size `size` (SPEC §4): `(6, size, size, 4)` float32,
/// faces in the order +X, −X, +Y, −Y, +Z, −Z.
#[pyfunction]
fn cube_map(py: Python<'_>, size: usize) -> PyResult<Bound<'_, PyAny>> {
    if !(1..=4096).contains(&size) {
        return Err(raise(py, Error::param("size", format!("{size}: 1..=4096"))));
    }
    let v = py.detach(|| horizon_bake::kernels::cubemap::cube_factors(size));
    array(py, v, &[6, size, size, 4])
}

/// `horizon-bake ARGS…` exactly as the command line runs it (ARGS without the program name),
/// the GIL released. Errors are the CLI's: a flag clap refuses is a ParameterError with the
/// line the CLI prints, the rest as [`raise`].
#[pyfunction]
fn run_cli(py: Python<'_>, args: Vec<String>) -> PyResult<()> {
    use clap::Parser;
    let argv = std::iter::once("horizon-bake".to_owned()).chain(args);
    let cli = match horizon_bake::cli::Cli::try_parse_from(argv) {
        Ok(cli) => cli,
        Err(e) => {
            let msg = horizon_bake::cli::usage_error_line(&e);
            return Err(raise_as(py, "ParameterError", &msg, "invalid_parameter", None));
        }
    };
    py.detach(|| horizon_bake::cli::run(cli)).map_err(|e| raise(py, e))
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(bake_array, m)?)?;
    m.add_function(wrap_pyfunction!(cube_map, m)?)?;
    m.add_function(wrap_pyfunction!(resolve, m)?)?;
    m.add_function(wrap_pyfunction!(bake_block, m)?)?;
    m.add_function(wrap_pyfunction!(run_cli, m)?)?;
    m.add("CRATE_VERSION", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
