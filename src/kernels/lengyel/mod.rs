//! The Lengyel/Max horizon map (SPEC §3.1): [`LengyelNaive`], the specification's loop written
//! the plain way (the oracle, [`oracle`]), and [`LengyelFast`], the same function vectorised
//! across texels ([`fast`]), tested against it on random inputs and on the golden files.

pub mod fast;
pub mod oracle;

pub use fast::LengyelFast;
pub use oracle::LengyelNaive;
