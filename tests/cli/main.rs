//! The real `horizon-bake` binary as a user runs it: `bake`, `cubemap`, `preview` and their
//! refusals against the golden files, `preview` on pipes and
//! contact sheets, and the eval (SPEC §4) with `radius=auto`.

#[path = "../support/mod.rs"]
mod support;

mod cli;
mod eval;
mod previews;
