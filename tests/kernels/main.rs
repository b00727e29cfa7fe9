//! The kernels and what is computed from them, one module per kernel or property: `exact`
//! against a brute-force march, `sweep` and `march` against their oracles and `exact`,
//! `lengyel_fast` against the plain oracle, the Fourier encoding, symmetry properties, the golden
//! acceptance cases, numerical extremes, and shading and previews.

#[path = "../support/mod.rs"]
mod support;

mod exact;
mod extremes;
mod fourier;
mod golden;
mod lengyel_fast;
mod march;
mod properties;
mod shading;
mod surface;
mod sweep;
