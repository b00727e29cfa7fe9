//! Terrain products (SPEC §3.7): what terrain and solar users take from the horizons the
//! kernels compute. Pure functions of per-bin horizon values (sin α at φ_n = n·360°/bins, as
//! [`crate::kernels::HorizonRows::rows`] writes them before any channel reduction): no I/O, no
//! decoding, no encoding.
//!
//! - [`angles`]: horizon angles per azimuth band, in the unit and azimuth convention asked.
//! - [`svf`]: the sky-view factor, radiative, visual or tilted.
//! - [`profile`]: the horizon profile at one point.
//! - [`shadow`]: lit or shadowed for a sun position.
//! - [`sun`]: the sun position of a time and place (NREL SPA).
//! - [`surface`]: normal, ambient occlusion and bent normal (SPEC §3.8), from the same horizons.

pub mod angles;
pub mod profile;
pub mod shadow;
pub mod sun;
pub mod surface;
pub mod svf;
