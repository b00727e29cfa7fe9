//! Terrain products (SPEC §3.7): what terrain and solar users take from the horizons the
//! kernels compute. Pure functions of per-bin horizon values (sin α at φ_n = n·360°/bins, as
//! [`crate::kernels::HorizonRows::rows`] writes them before any channel reduction): no I/O, no
//! decoding, no encoding.
//!
//! - [`angles`]: horizon angles per azimuth band, in the unit and azimuth convention asked.
//! - [`svf`]: the sky-view factor, radiative or visual.
//! - [`profile`]: the horizon profile at one point.

pub mod angles;
pub mod profile;
pub mod svf;
