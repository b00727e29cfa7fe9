//! The command-line interface: clap definitions and one module per subcommand (SPEC §6).
//!
//! Each subcommand parses its flags into library types and calls the library; none of them does
//! arithmetic on pixels. Errors come back as [`crate::Error`] and `main` prints them on one line.

pub mod bake;
pub mod cubemap;
pub mod eval;
pub mod preview;
pub mod profile;
pub mod serve;
pub mod shaders;
pub mod shadow;

use clap::{Parser, Subcommand};

/// Bakes horizon maps for self-shadowing of normal-mapped surfaces.
#[derive(Debug, Parser)]
#[command(name = "horizon-bake", version, about)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

/// The subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run the HTTP bake service.
    Serve(Box<serve::ServeArgs>),
    /// Bake one height map into horizon layers (and Fourier coefficients) in a directory.
    Bake(bake::BakeArgs),
    /// Write the channel-factor cube map.
    Cubemap(cubemap::CubemapArgs),
    /// Write the shader includes (GLSL, HLSL, WGSL, Godot) and their examples.
    Shaders(shaders::ShadersArgs),
    /// Render a CPU preview of the shading.
    Preview(preview::PreviewArgs),
    /// Measure accuracy against the exact ground truth, beside the time (SPEC §4).
    Eval(eval::EvalArgs),
    /// Print the exact horizon profile at one point (CSV, or JSON with --json).
    Profile(profile::ProfileArgs),
    /// Write the sun shadow of a height map or DEM as a GeoTIFF.
    Shadow(shadow::ShadowArgs),
}

/// The one line a refused command line is reported with (SPEC §6): clap's first paragraph,
/// which says what was wrong (sometimes over two lines, e.g. the missing flags), without the
/// tips and usage that follow a blank line, and without clap's `error: `. `main` prints it after
/// `horizon-bake: `; the Python package raises it.
pub fn usage_error_line(e: &clap::Error) -> String {
    let text = e.render().to_string();
    let first: Vec<&str> = text
        .lines()
        .map(str::trim)
        .take_while(|l| !l.is_empty() && !l.starts_with("Usage:"))
        .collect();
    first.join(" ").trim_start_matches("error: ").to_owned()
}

/// Runs a parsed command line.
///
/// # Errors
/// Whatever the subcommand fails with.
pub fn run(cli: Cli) -> crate::Result<()> {
    match cli.command {
        Command::Serve(a) => serve::run(*a),
        Command::Bake(a) => bake::run(a),
        Command::Cubemap(a) => cubemap::run(a),
        Command::Shaders(a) => shaders::run(a),
        Command::Preview(a) => preview::run(a),
        Command::Eval(a) => eval::run(a),
        Command::Profile(a) => profile::run(a),
        Command::Shadow(a) => shadow::run(a),
    }
}
