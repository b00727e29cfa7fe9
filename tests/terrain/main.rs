//! Height-map input and terrain users: every supported layout decodes to known values with a
//! clear error for each broken one (`inputs`), DEM input, nodata, terrain products and GeoTIFF
//! output (`terrain`; its GDAL read-back script is `check_dem.py` beside this file).

#[path = "../support/mod.rs"]
mod support;

mod inputs;
mod terrain;
