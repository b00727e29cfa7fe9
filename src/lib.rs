//! horizon-bake: horizon maps for self-shadowing of normal-mapped surfaces.
//!
//! # Layout
//! Data flows one way: decode → bake → encode → store → serve.
//!
//! - [`heightmap`]: decode and validate an input image into heights (limits checked before any
//!   pixel buffer is allocated).
//! - [`params`]: every bake parameter, parsed the same way from JSON, query strings and flags.
//! - [`kernels`]: pure numeric code over slices, a folder or file per technique with its oracle
//!   beside it: the Lengyel horizon map, the exact line-of-sight horizon and the near field it
//!   shares with `sweep`, `march`, the channel-factor cube map, Fourier encoding and the
//!   shading used by previews; [`kernels::isa`] picks the compiled variant at run time.
//! - [`layers`]: the horizon layers and quantisers, the leaf that bake and encode both use.
//! - [`bake`]: parameters → kernels → quantised layers (or rows streamed to a sink), with
//!   progress and cancellation; which kernel fits which map is decided here, once.
//! - [`terrain`]: terrain products (angles per azimuth, sky-view factor) from per-bin horizons.
//! - [`encode`]: PNG 8/16, OpenEXR, KTX2, DDS and GeoTIFF writers; the engine-ready textures of
//!   SPEC §8 (mip filters, BC7/BC5 blocks, zstd, layouts, DDS headers).
//! - [`pipeline`]: the one bake pipeline, decoded map → encoded files in a sink, shared by the
//!   CLI and the service; its `terrain` GeoTIFF products, `job` (a stored bake record run into
//!   the blob store) and `tiled` (split, a tile's bake, assembly).
//! - [`preview`]: the CPU preview of the shading (and the contact sheet), as PNG.
//! - [`eval`]: the accuracy/time trade of every model against the exact ground truth (SPEC §4).
//! - [`shaders`]: the shader includes (GLSL, HLSL, WGSL, Godot) that decode the maps in an
//!   engine, embedded in the binary; the web viewer compiles the GLSL one.
//! - [`cli`]: the `horizon-bake` subcommands, thin wrappers over the above.
//! - [`jobs`]: the job lifecycle behind the repository and blob-store traits: the record model,
//!   embedded (redb + files) on one machine, PostgreSQL + S3 across many; the worker loop with
//!   leases and the coordination of tiled bakes.
//! - [`service`]: the HTTP job service (axum): thin handlers that wire [`jobs`] and
//!   [`pipeline`], problem+json.
//!
//! docs/architecture.md draws the flow and says why each part sits where it does.
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
pub mod shaders;
pub mod terrain;

pub use error::{Error, Result};
