//! horizon-bake: horizon maps for self-shadowing of normal-mapped surfaces.
//!
//! # Layout
//! Data flows one way: decode → bake → encode → store → serve.
//!
//! - [`heightmap`]: decode and validate an input image into heights (limits checked before any
//!   pixel buffer is allocated).
//! - [`params`]: every bake parameter, parsed the same way from JSON, query strings and flags.
//! - [`kernels`]: pure numeric code over slices: the Lengyel horizon map (plain oracle and fast
//!   version), the exact line-of-sight horizon, the channel-factor cube map, Fourier encoding and
//!   the shading used by previews.
//! - [`encode`]: PNG 8/16, OpenEXR, KTX2 and DDS writers.
//! - [`preview`]: the CPU preview of the shading (and the contact sheet), as PNG.
//! - [`bake`]: one bake = parameters → kernels → encoded outputs, with progress and cancellation.
//! - [`eval`]: the accuracy/time trade of every model against the exact ground truth (SPEC §4).
//! - [`cli`]: the `horizon-bake` subcommands, thin wrappers over the above.
//! - [`service`]: the HTTP job service (axum): queue, rayon bake pool, store, problem+json.
//! - [`error`]: the one error type, whose variants say whose fault a failure is.

pub mod bake;
pub mod cli;
pub mod encode;
pub mod error;
pub mod eval;
pub mod heightmap;
pub mod jobs;
pub mod kernels;
pub mod layers;
pub mod params;
pub mod pipeline;
pub mod preview;
pub mod progress;
pub mod service;

pub use error::{Error, Result};
