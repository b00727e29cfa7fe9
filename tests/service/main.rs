//! The HTTP service in this process (servers on 127.0.0.1:0, or `app(state)` via `oneshot`) and
//! as the real binary, a module per feature: the API end to end, submissions and their
//! refusals, results and their downloads, cancellation, listing and retention, HTTP details
//! (security headers, keys, limits, request ids), hostile input and full disks, previews,
//! uploads, texture variants, the documentation's promises, the decoders and parsers under
//! fuzzing, and the process itself (SIGKILL, SIGTERM, the log).

#[path = "../support/mod.rs"]
mod support;

mod api;
mod cancel;
mod decode_budget;
mod docs;
mod fuzz;
mod hostile;
mod http;
mod previews;
mod process;
mod records;
mod results;
mod submissions;
mod textures;
mod uploads;
